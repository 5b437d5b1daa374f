"""marbler-jax: the Robotarium and MARBLER's multi-robot tasks, batched in JAX.

Submodules:
    physics      -- unicycle kinematics, actuator limits, arena checks (rps-exact).
    controllers  -- goal-to-velocity controllers and SI <-> unicycle maps.
    cbf          -- barrier certificates as fixed-iteration batched QP solvers.
    env          -- the batched env core (MARBLER's control loop); scenarios -- the tasks.

``make(name, **overrides)`` builds an env, ``registered()`` lists scenario names.
"""
from __future__ import annotations

__version__ = "0.1.0"

try:
    import jax
except ImportError:         # numpy-only use: marbler_jax.numpy_policy and the Robotarium bundle's modules
    jax = None

if jax is not None:
    from marbler_jax import cbf, controllers, physics

    # Configuration dataclasses are hashable constants: register them as pytrees without leaves so
    # they can be passed straight through jit/vmap boundaries.
    jax.tree_util.register_static(physics.RobotariumParams)
    jax.tree_util.register_static(cbf.Barrier)

    from marbler_jax.registry import make, register, registered  # noqa: E402

# gymnasium ids (marbler_jax/<Scenario>-v0) are registered through the package's gymnasium.envs entry point.
__all__ = ["physics", "controllers", "cbf", "make", "register", "registered", "__version__"]
