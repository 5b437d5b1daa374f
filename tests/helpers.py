"""Small helpers shared by the tests."""
from __future__ import annotations


def load_script(name: str, folder: str = "scripts"):
    """A module of ``scripts/`` (or another folder that is not a package) loaded from its file."""
    import importlib.util
    import sys
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / folder / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module          # dataclasses (flax modules) look their module up while it runs
    spec.loader.exec_module(module)
    return module


def load_example(name: str):
    """A module of ``examples/`` loaded from its file."""
    return load_script(name, "examples")


def slow_unless(values, default) -> list:
    """``values`` as pytest parameters: those in ``default`` run by default, the others under ``-m slow``."""
    import pytest

    return [v if v in default else pytest.param(v, marks=pytest.mark.slow) for v in values]


def interrupt_at(update: int):
    """An ``on_chunk`` callback that simulates Ctrl-C once chunk ``update`` has been saved."""
    def on_chunk(done: int) -> None:
        if done == update:
            raise KeyboardInterrupt

    return on_chunk


def compile_marks(train, **kwargs) -> list[int]:
    """Runs ``train(**kwargs)`` (the training driver's) and returns how many XLA compilations had happened
    at its "compiled in" line and after each chunk: equal marks mean nothing compiled inside the loop."""
    import jax

    compiles, marks = [], []

    def on_event(name, seconds, **kw):
        if name == "/jax/core/compile/backend_compile_duration":
            compiles.append(name)

    def log(message):
        if message.startswith("compiled in"):
            marks.append(len(compiles))

    jax.monitoring.register_event_duration_secs_listener(on_event)
    try:
        train(on_chunk=lambda done: marks.append(len(compiles)), log=log, **kwargs)
    finally:
        jax.monitoring.unregister_event_duration_listener(on_event)
    return marks


def tensorboard_steps(folder) -> dict[str, list[int]]:
    """``{tag: [step, ...]}`` over every event file in ``folder`` (TFRecord framing: length, its CRC,
    the serialized ``Event``, its CRC), in file order."""
    import struct
    from pathlib import Path

    from tensorboardX.proto.event_pb2 import Event

    steps: dict[str, list[int]] = {}
    for file in sorted(Path(folder).glob("events.out.tfevents.*")):
        data = file.read_bytes()
        at = 0
        while at < len(data):
            (length,) = struct.unpack_from("<Q", data, at)
            event = Event.FromString(data[at + 12: at + 12 + length])
            at += 12 + length + 4
            for value in event.summary.value:
                steps.setdefault(value.tag, []).append(event.step)
    return steps


def initial_params(module, env, cfg, seed: int = 0):
    """The untrained parameters ``module.make_train(env, cfg).init`` draws from ``PRNGKey(seed)``, from a
    program that computes nothing else (the envs, buffers and optimiser state of the full init are pruned)."""
    import jax

    init = module.make_train(env, cfg).init
    return jax.jit(lambda key: init(key)["params"])(jax.random.PRNGKey(seed))


def run_with_two_devices(script: str, *args: str) -> None:
    """Runs ``script`` (which asks JAX for two CPU devices before it first runs) in a fresh interpreter from
    the repository root; it must print ``ok`` last."""
    import subprocess
    import sys
    from pathlib import Path

    result = subprocess.run([sys.executable, "-c", script, *args], cwd=Path(__file__).resolve().parents[1],
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0 and result.stdout.strip().endswith("ok"), result.stdout + result.stderr
