"""``marbler-jax benchmark`` and ``report``: the results file, its statistics and a tiny resumable grid."""
from __future__ import annotations

import json
import re

import jax
import numpy as np
import pytest

from marbler_jax_rl import benchmark, report
from marbler_jax_rl.benchmark import ABSOLUTE, ENV_NAME, finished_cells, grid, load_results, run_benchmark

pytest.importorskip("rliable")


def _runs(rewards_per_run, best_test=None, steps=(100, 200), recipe=None):
    runs = {}
    for k, rewards in enumerate(rewards_per_run):
        entry = {f"step_{i}": {"step_count": s, "reward": [float(r) * (i + 1) / len(steps) for r in rewards]}
                 for i, s in enumerate(steps)}
        entry[ABSOLUTE] = {"reward": [float(r) for r in rewards], "steps": [50.0] * len(rewards),
                           "collisions": [0.0] * len(rewards), "out_of_bounds": [0.0] * len(rewards),
                           "best_test_return": [float(best_test[k] if best_test else np.mean(rewards))],
                           "env_steps": [steps[-1]], "train_seconds": [10.0]}
        if recipe:
            entry[ABSOLUTE]["recipe"] = [recipe]
        runs[f"run_{k}"] = entry
    return runs


def test_dry_run_estimates_time_from_the_rates_cells_trained_at():
    """``--dry-run``: each cell's time at the rate the same cell trained at on this kind of device (two runs x
    200 env steps in 10 s: 40 env-steps/s), the unmeasured cells named."""
    runs = _runs([[1.0], [2.0]])
    for run in runs.values():
        run[ABSOLUTE]["device"] = ["cpu"]
    gpu = _runs([[1.0]])
    gpu["run_0"][ABSOLUTE]["device"] = ["NVIDIA H100"]
    results = {ENV_NAME: {"warehouse": {"vdn": runs, "qmix": gpu}}}
    rates = benchmark.measured_rates(results, "cpu")
    assert rates == {("warehouse", "vdn"): 40.0}
    plans = [benchmark.CellPlan("warehouse", algo, {}, {}, 72_000, "d", 10, "new") for algo in ("vdn", "qmix")]
    text = benchmark.describe_plan(plans, 2, "x/results.json", rates, "results/old").splitlines()
    assert text[1].endswith("new; ~1.0 h") and text[2].endswith("new")          # 144,000 env steps at 40/s
    assert text[-1].startswith("estimated 1.0 h of updates at the rates its cells trained at in results/old")
    assert text[-1].endswith("no measurement for warehouse/qmix")


def test_results_files_merge_and_name_their_cells(tmp_path):
    a = {ENV_NAME: {"warehouse": {"vdn": _runs([[1.0]])}}}
    b = {ENV_NAME: {"warehouse": {"qmix": _runs([[2.0]])}, "predator_capture_prey": {"vdn": _runs([[3.0]])}}}
    (tmp_path / "results-p0.json").write_text(json.dumps(a))
    (tmp_path / "results-p1.json").write_text(json.dumps(b))
    merged = load_results(tmp_path)
    assert finished_cells(merged) == {("warehouse", "vdn"), ("warehouse", "qmix"), ("predator_capture_prey", "vdn")}
    assert merged[ENV_NAME]["warehouse"]["qmix"] == b[ENV_NAME]["warehouse"]["qmix"]
    (tmp_path / "results-p1.json").write_text("{broken")
    with pytest.raises(ValueError, match="results-p1.json is not valid JSON"):
        load_results(tmp_path)


@pytest.mark.parametrize("content, entry", [
    ([1, 2], "results.json holds a JSON list"),
    ({ENV_NAME: []}, "results.json: marbler is not an object of scenarios"),
    ({ENV_NAME: {"warehouse": {"vdn": {}}}}, "results.json: marbler/warehouse/vdn is not a non-empty object of runs"),
    ({ENV_NAME: {"warehouse": {"vdn": {"seed0": {}}}}}, "results.json: marbler/warehouse/vdn has an entry 'seed0'"),
    ({ENV_NAME: {"warehouse": {"vdn": {"run_0": {"step_0": {}}}}}}, "results.json: marbler/warehouse/vdn/run_0 has no 'absolute_metrics'"),
    ({ENV_NAME: {"warehouse": {"vdn": {"run_0": {ABSOLUTE: {"reward": "high"}}}}}},
     "results.json: marbler/warehouse/vdn/run_0 absolute_metrics/reward is not a list of numbers"),
    ({ENV_NAME: {"warehouse": {"vdn": {"run_0": {ABSOLUTE: {"reward": [1.0]}, "step_0": {"reward": [1.0]}}}}}},
     "results.json: marbler/warehouse/vdn/run_0 step_0 has no step_count"),
])
def test_a_results_file_of_the_wrong_shape_is_one_line_naming_the_file_and_the_entry(tmp_path, capsys, content,
                                                                                      entry):
    """Valid JSON of the wrong shape gave AttributeError / IndexError / StopIteration tracebacks in report and
    benchmark."""
    from marbler_jax_rl.cli import main as cli

    (tmp_path / "results.json").write_text(json.dumps(content))
    with pytest.raises(ValueError, match=re.escape(entry)):
        load_results(tmp_path)
    for argv in (["report", str(tmp_path), "--no-progress"],
                 ["benchmark", "--out", str(tmp_path), "--scenarios", "warehouse", "--algos", "vdn", "--dry-run"]):
        assert cli(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and entry in err[0], err


def test_grid_canonicalises_and_shares_cells_between_processes():
    cells = grid(["vdn", "qmix"], ["pcp", "warehouse"])
    assert cells == [("predator_capture_prey", "vdn"), ("predator_capture_prey", "qmix"), ("warehouse", "vdn"),
                     ("warehouse", "qmix")]
    assert grid(["vdn", "qmix"], ["pcp", "warehouse"], 1, 2) == [cells[1], cells[3]]
    with pytest.raises(ValueError, match="unknown algorithm"):
        grid(["dqn"], ["warehouse"])
    with pytest.raises(ValueError, match="names a cell twice"):
        grid(["vdn"], ["pcp", "predator_capture_prey"])


def test_iqm_and_its_interval_on_known_scores():
    iqm, low, high = report.iqm_ci(np.arange(8.0), reps=200)
    scores = np.array([32.28, 32.62, 32.63, 32.75, 33.06])
    assert len({report.iqm_ci(scores, reps=500) for _ in range(4)}) == 1     # the same report every time
    assert iqm == pytest.approx(3.5)              # the middle half: 2, 3, 4, 5
    assert low <= iqm <= high and low >= 0 and high <= 7
    assert report.iqm_ci(np.full(5, 2.5), reps=50) == pytest.approx((2.5, 2.5, 2.5))


def test_probability_of_improvement_on_known_scores():
    assert report.probability_of_improvement([3.0, 4.0], [1.0, 2.0], reps=50) == pytest.approx((1.0, 1.0, 1.0))
    assert report.probability_of_improvement([1.0], [1.0], reps=50)[0] == pytest.approx(0.5)   # ties count half
    # x = [1, 3] against y = [2]: one win, one loss
    assert report.probability_of_improvement([1.0, 3.0], [2.0], reps=50)[0] == pytest.approx(0.5)


def test_best_seed_is_the_best_test_return_and_reached_compares_with_the_paper():
    runs = _runs([[30.0, 32.0], [34.0, 36.0], [20.0, 22.0]], best_test=[33.0, 31.0, 40.0])
    assert report.best_seed_run(runs) == "run_2"           # picked by training-time test, not by evaluation
    assert report.reached("reward", 33.3, 33.25) and not report.reached("reward", 33.2, 33.25)
    assert report.reached("steps", 50.0, 55.0) and not report.reached("prey_left", 0.1, 0.0)
    assert report.reached("collisions", 1.0, None) and not report.reached("out_of_bounds", 1.5, None)
    assert report.reached("reward", 1.0, None) is None


def test_training_time_is_summed_per_device():
    gpu, cpu = _runs([[1.0]]), _runs([[1.0]])
    gpu["run_0"][ABSOLUTE].update(train_seconds=[1800.0], device=["NVIDIA H100 80GB HBM3"])
    cpu["run_0"][ABSOLUTE].update(train_seconds=[3600.0], device=["cpu"])
    tasks = {"a": {"vdn": cpu, "qmix": _runs([[1.0]])}, "b": {"vdn": dict(cpu), "mappo": gpu}}
    assert report.training_time(tasks) == ("2.00 h on cpu (2 cells), 0.50 h on NVIDIA H100 80GB HBM3 (1 cell), "
                                           "0.00 h on device not recorded (1 cell)")


def test_wall_clock_names_every_device_that_trained_a_resumed_cell(tmp_path):
    first = benchmark.WallClock(tmp_path, resume=False, device="NVIDIA H200")
    first.save()
    assert first.device() == "NVIDIA H200"
    again = benchmark.WallClock(tmp_path, resume=True, device="NVIDIA H200")
    again.save()
    resumed = benchmark.WallClock(tmp_path, resume=True, device="cpu")
    resumed.save()
    saved = json.loads((tmp_path / benchmark.WALL_FILE).read_text())
    assert saved["devices"] == ["NVIDIA H200", "NVIDIA H200", "cpu"] and len(saved["invocations"]) == 3
    assert resumed.device() == "NVIDIA H200 + cpu"
    # a file written before devices were recorded: its invocations count, their device is not known
    (tmp_path / benchmark.WALL_FILE).write_text(json.dumps({"invocations": [10.0, 20.0]}))
    old = benchmark.WallClock(tmp_path, resume=True, device="cpu")
    assert old.save() >= 30.0 and old.device() == f"{benchmark.UNRECORDED_DEVICE} + cpu"
    assert benchmark.WallClock(tmp_path, resume=False, device="cpu").device() == "cpu"


def test_time_table_sums_the_paper_cells_apart_from_the_others():
    results = {ENV_NAME: {"predator_capture_prey": {"vdn": _runs([[1.0]]), "ippo": _runs([[1.0]])},
                          "rware": {"mappo": _runs([[1.0]])}}}
    for cell, (train, wall) in zip([("predator_capture_prey", "vdn"), ("predator_capture_prey", "ippo"),
                                    ("rware", "mappo")], [(3600.0, 3960.0), (1800.0, None), (7200.0, 7560.0)]):
        absolute = results[ENV_NAME][cell[0]][cell[1]]["run_0"][ABSOLUTE]
        absolute["train_seconds"] = [train]
        if wall is not None:
            absolute["wall_seconds"] = [wall]
    rows = report.time_table(results).splitlines()
    assert rows[-2] == "| the paper's 1 cells | | | | 1.00 h | 1.10 h |"       # IPPO has no paper value
    assert rows[-1] == "| all 3 cells | | | | 3.50 h | 3.20 h (2 of 3 cells recorded) |"
    only_paper = {ENV_NAME: {"predator_capture_prey": {"vdn": results[ENV_NAME]["predator_capture_prey"]["vdn"]}}}
    assert not any(row.startswith("| the paper's") for row in report.time_table(only_paper).splitlines())


def test_report_renders_tables_curves_and_improvement(tmp_path):
    from marbler_jax_rl.recipes import RECIPES

    current = RECIPES["vdn"].digest("predator_capture_prey")
    results = {ENV_NAME: {"predator_capture_prey": {
        "vdn": _runs([[33.0, 34.0], [30.0, 31.0]], recipe=current),
        "qmix": _runs([[20.0, 21.0], [25.0, 26.0]], recipe=current)}}}    # VDN's recipe made the QMIX cell
    for run in results[ENV_NAME]["predator_capture_prey"]["vdn"].values():
        run[ABSOLUTE].update(wall_seconds=[120.0], device=["cpu"])
    (tmp_path / "results.json").write_text(json.dumps(results))
    docs = tmp_path / "docs"
    docs.mkdir()
    readme = docs / "README.md"
    readme.write_text(f"# title\n\n{report.SUMMARY_START}\nan old table\n{report.SUMMARY_END}\n\nthe rest\n")
    written = report.write_report(tmp_path, reps=50, results_md=docs / "RESULTS.md", readme=readme)
    text = (tmp_path / "report.md").read_text()
    assert [p.name for p in written] == ["report.md", "curves_predator_capture_prey.png", "RESULTS.md", "README.md"]
    # the README's reward summary: the best seed bold where it reaches the paper, † off the recipe, — not run
    summary = readme.read_text().split(report.SUMMARY_START + "\n")[1].split(report.SUMMARY_END)[0]
    assert readme.read_text().startswith("# title\n\n") and readme.read_text().endswith("\n\nthe rest\n")
    rows = summary.splitlines()
    assert rows[0] == "| reward: ours, best seed (IQM [95 % CI]) / paper | VDN | QMIX | QMIX_NS | MAPPO |"
    assert rows[2].startswith("| Predator Capture Prey | **33.50** (32.00 [") and " / 33.25 | 25.50† (" in rows[2]
    assert rows[2].endswith(" / 30.02 | — / 31.76 | — / 23.48 |") and len(rows) == 6
    assert rows[5] == "| Arctic Transport | — / \u22126.98 | — / \u22127.13 | — / \u221211.29 | — / \u22127.23 |"
    page = (docs / "RESULTS.md").read_text()
    assert "marbler-jax report results/marbler-table2 --results-md RESULTS.md" in page
    assert "](../curves_predator_capture_prey.png)" in page             # relative to the page
    assert "qmix_ns on predator_capture_prey" in page.split("Cells not in the results yet")[1]
    assert "| predator_capture_prey | vdn | 2 | 0.0M | 32.00 [" in text
    assert "| predator_capture_prey | qmix† | 2 |" in text and "† trained with other settings" in text
    assert "| 33.50 ± 0.50 | 33.25 ± 0.46 | yes |" in text       # best seed run_0 against the paper
    assert "| qmix | 0.00 [0.00, 0.00] | — |" in text              # P(qmix > vdn)
    times = text.split("### Time per cell")[1].split("###")[0]
    assert "| predator_capture_prey | vdn | 0.0M | cpu | 0.2 min | 2.0 min |" in times
    assert "| predator_capture_prey | qmix† | 0.0M | device not recorded | 0.2 min | — |" in times
    assert "| all 2 cells | | | | 0.01 h | 0.03 h (1 of 2 cells recorded) |" in times
    assert (tmp_path / "curves_predator_capture_prey.png").stat().st_size > 1000
    with pytest.raises(ValueError, match="no cell yet"):
        report.report_markdown({})
    unmarked = docs / "plain.md"
    unmarked.write_text("no markers\n")
    with pytest.raises(ValueError, match="plain.md has no reward summary to replace: put the lines"):
        report.write_report(tmp_path, reps=50, readme=unmarked)
    assert unmarked.read_text() == "no markers\n"


def test_report_marks_a_cell_made_with_its_recipes_own_settings_for_the_scenario(monkeypatch):
    import dataclasses

    from marbler_jax_rl.recipes import RECIPES

    own = dataclasses.replace(RECIPES["vdn"], scenario_hp={"predator_capture_prey": {"gamma": 0.99}},
                              why={"predator_capture_prey": "the prey pay late."})
    monkeypatch.setattr(report, "RECIPES", dict(RECIPES, vdn=own))
    results = {ENV_NAME: {"predator_capture_prey": {
        "vdn": _runs([[33.0, 34.0], [30.0, 31.0]], recipe=own.digest("predator_capture_prey")),
        "qmix": _runs([[20.0, 21.0], [25.0, 26.0]], recipe=RECIPES["qmix"].digest("predator_capture_prey"))}}}
    text = report.report_markdown(results, reps=20)
    assert "| predator_capture_prey | vdn‡ | 2 |" in text and "| predator_capture_prey | qmix | 2 |" in text
    assert ("‡ vdn on predator_capture_prey: the recipe's own settings for this scenario (`gamma=0.99`): "
            "the prey pay late.") in text
    assert "†" not in text
    assert "| Predator Capture Prey | **33.50**‡ (" in report.summary_table(results, reps=20)
    # two algorithms with the same settings and reason share one note
    own_q = dataclasses.replace(RECIPES["qmix"], scenario_hp=own.scenario_hp, why=own.why)
    monkeypatch.setattr(report, "RECIPES", dict(RECIPES, vdn=own, qmix=own_q))
    results[ENV_NAME]["predator_capture_prey"] = {     # results-file order is not the table's
        "qmix": _runs([[20.0, 21.0]], recipe=own_q.digest("predator_capture_prey")),
        "vdn": results[ENV_NAME]["predator_capture_prey"]["vdn"]}
    shared = report.report_markdown(results, reps=20)
    assert ("‡ vdn and qmix on predator_capture_prey: the recipe's own settings for this scenario (`gamma=0.99`): "
            "the prey pay late.") in shared and shared.count("the prey pay late.") == 1
    monkeypatch.setattr(report, "RECIPES", dict(RECIPES, vdn=own))
    # the same cell made with the recipe's common settings is off the recipe now
    results[ENV_NAME]["predator_capture_prey"]["vdn"] = _runs([[33.0, 34.0]], recipe=RECIPES["vdn"].digest(
        "predator_capture_prey"))
    assert "| predator_capture_prey | vdn† | 1 |" in report.report_markdown(results, reps=20)


def test_report_shows_the_paper_models_score_beside_each_cell(tmp_path):
    """``--paper-models DIR``: each cell's row carries the paper's own model's score (mean ± 95 % CI over its
    episodes) from ``evaluate --json`` files; a cell without one shows —."""
    (tmp_path / "results.json").write_text(json.dumps({ENV_NAME: {"warehouse": {
        "vdn": _runs([[30.0, 31.0], [20.0, 22.0]]), "qmix": _runs([[10.0, 12.0], [15.0, 14.0]])}}}))
    models = tmp_path / "models"
    models.mkdir()
    (models / "warehouse-vdn.json").write_text(json.dumps(dict(scenario="warehouse", algo="vdn", episodes_metrics={
        "reward": [28.0, 30.0, 29.0, 31.0]})))
    report.write_report(tmp_path, reps=20, paper_models=models)
    text = (tmp_path / "report.md").read_text()
    assert "| paper | paper's model, here (mean ± 95 % CI) | reached |" in text
    half = 1.96 * np.std([28.0, 30.0, 29.0, 31.0], ddof=1) / 2
    assert f"| 28.7 ± 1.49 | 29.50 ± {half:.2f} | " in text
    qmix = next(line for line in text.splitlines() if line.startswith("| warehouse | qmix"))
    assert qmix.endswith("| 27.4 ± 1.02 | — | no |") or qmix.endswith("| 27.4 ± 1.02 | — | **no** |")
    with pytest.raises(ValueError, match="--paper-models .*nowhere is not a folder"):
        report.write_report(tmp_path, reps=20, paper_models=tmp_path / "nowhere")


def test_report_shows_its_progress_unless_told_not_to(tmp_path, capsys):
    """The report's bootstraps take minutes on a whole table: the command shows a bar over its parts."""
    from marbler_jax_rl.cli import main as cli

    results = {ENV_NAME: {"warehouse": {"vdn": _runs([[30.0, 31.0], [20.0, 22.0]])},
                          "predator_capture_prey": {"vdn": _runs([[30.0, 31.0], [20.0, 22.0]])}}}
    (tmp_path / "results.json").write_text(json.dumps(results))
    assert cli(["report", str(tmp_path), "--reps", "20"]) == 0
    err = capsys.readouterr().err
    assert "tables" in err and "3/3" in err and "curves of warehouse" in err
    assert cli(["report", str(tmp_path), "--reps", "20", "--no-progress"]) == 0
    assert capsys.readouterr().err == ""


def test_a_second_report_bootstraps_only_what_changed(tmp_path, monkeypatch):
    from rliable import library

    calls = []
    original = library.get_interval_estimates
    monkeypatch.setattr(library, "get_interval_estimates", lambda *a, **kw: calls.append(1) or original(*a, **kw))
    results = {ENV_NAME: {"warehouse": {"vdn": _runs([[30.0, 31.0], [20.0, 22.0], [25.0, 24.0]]),
                                        "qmix": _runs([[10.0, 12.0], [15.0, 14.0], [20.0, 19.0]])}}}
    (tmp_path / "results.json").write_text(json.dumps(results))
    report.write_report(tmp_path, reps=50)
    first, cold = (tmp_path / "report.md").read_text(), len(calls)
    assert cold > 0 and (tmp_path / report.CACHE_FILE).exists()
    calls.clear()
    report.write_report(tmp_path, reps=50)
    assert not calls and (tmp_path / "report.md").read_text() == first      # the same numbers, none recomputed
    results[ENV_NAME]["warehouse"]["qmix"] = _runs([[11.0, 12.0], [15.0, 14.0], [20.0, 19.0]])
    (tmp_path / "results.json").write_text(json.dumps(results))
    report.write_report(tmp_path, reps=50)
    text = (tmp_path / "report.md").read_text()
    vdn_row = next(line for line in first.splitlines() if line.startswith("| warehouse | vdn"))
    assert vdn_row in text and text != first
    assert len(calls) == 4          # the changed cell's curve and reward, P(vdn > qmix) and P(qmix > vdn)
    calls.clear()
    report.write_report(tmp_path, reps=60)
    assert len(calls) == cold                                                # other bootstraps: all again
    (tmp_path / report.CACHE_FILE).write_text("{not json")                    # a damaged cache is ignored
    calls.clear()
    report.write_report(tmp_path, reps=50)
    assert len(calls) == cold and (tmp_path / "report.md").read_text() == text


def test_jaxrobotarium_scenarios_follow_the_paper_and_task_metrics_and_success_get_tables():
    from marbler_jax_rl.recipes import RECIPES

    discovery = _runs([[5.0, 6.0], [7.0, 8.0]], recipe=RECIPES["vdn"].digest("discovery"))
    for entry in discovery.values():
        entry[ABSOLUTE]["landmarks_left"] = [1.0, 0.0]
    pcp = _runs([[30.0], [31.0]], recipe=RECIPES["vdn"].digest("predator_capture_prey"))
    results = {ENV_NAME: {"discovery": {"vdn": discovery}, "predator_capture_prey": {"vdn": pcp}}}
    rewards = report.metric_table(results, "reward", reps=50)
    assert rewards.index("| predator_capture_prey | vdn |") < rewards.index("| discovery | vdn |")
    landmarks = report.metric_table(results, "landmarks_left", reps=50)
    assert landmarks.startswith("### Landmarks left (Discovery)")
    assert "| discovery | vdn | 2 | 0.0M | 0.50 [" in landmarks and "predator_capture_prey" not in landmarks
    # success: the share of episodes with nothing of the task left, over the scenarios that count what is left
    pcp["run_0"][ABSOLUTE]["prey_left"], pcp["run_1"][ABSOLUTE]["prey_left"] = [0.0], [2.0]
    results[ENV_NAME]["warehouse"] = {"vdn": _runs([[20.0], [21.0]])}
    success = report.metric_table(results, "success", reps=50)
    assert success.startswith("### Success (% of episodes that end with no prey, material, landmarks or resources")
    assert "| discovery | vdn | 2 | 0.0M | 50.00 [50.00, 50.00] | 50.00 ± 50.00 | — | — |" in success
    assert "| predator_capture_prey | vdn | 2 | 0.0M | 50.00 [0.00, 100.00] | 0.00 ± 0.00 |" in success  # best: run_1
    assert "warehouse" not in success


def test_tiny_benchmark_writes_resumes_and_reports(tmp_path):
    """2 algorithms x 1 scenario x 2 seeds on a tiny budget; killed in its second cell, rerun: the first
    cell is not trained again and the second resumes from its checkpoint."""
    out, logs = tmp_path / "bench", []
    kwargs = dict(algos=["ippo", "mappo"], scenarios=["simple"], seeds=2, total_steps=3 * 1024, eval_points=3,
                  test_episodes=4, absolute_factor=2, progress=False, log=logs.append)
    with pytest.raises(ValueError, match=rf"devices={jax.local_device_count() + 1} but this process has "):
        run_benchmark(out, **dict(kwargs, devices=jax.local_device_count() + 1))
    assert not out.exists()
    from marbler_jax_rl import recipes

    small = {a: recipes.Recipe(a, type(r.config)(num_envs=16, num_steps=64, hidden=16), steps=r.steps)
             for a, r in recipes.RECIPES.items() if a in ("ippo", "mappo")}

    class Interrupted(Exception):
        pass

    def stop_in_second_cell(update):
        if any("cell 2/2" in line for line in logs) and update == 1:
            raise Interrupted

    kwargs["recipes"] = small
    with pytest.raises(Interrupted):
        run_benchmark(out, on_chunk=stop_in_second_cell, **kwargs)
    first = json.loads((out / "results.json").read_text())
    assert finished_cells(first) == {("simple_navigation", "ippo")}
    # what a rerun will do, before it runs: the first cell is done, the second resumes from its checkpoint
    plan_args = {k: kwargs[k] for k in ("algos", "scenarios", "seeds", "total_steps", "test_episodes", "recipes")}
    plans = benchmark.plan_cells(out, **plan_args)
    assert [(p.algo, p.status, p.checkpoint, p.updates, p.replaces) for p in plans] == [
        ("ippo", "done", None, 3, False), ("mappo", "resume", 1, 3, False)]
    assert benchmark.remaining_steps(plans[1], 2) == 2 * 2 * 1024
    text = benchmark.describe_plan(plans, 2, "bench/results.json").splitlines()
    assert text[0] == "bench/results.json: 2 cell(s), 1 done, 1 resume; 4,096 env steps to train (2 seed(s) per cell)"
    assert text[2].endswith("resume from update 1 of 3")
    logs.clear()
    other = _runs([[1.0, 2.0]])

    def another_process_adds_a_cell(update):      # a concurrent benchmark writes into the same file
        benchmark.add_cell(out / "results.json", "warehouse", "vdn", other)

    results = run_benchmark(out, on_chunk=another_process_adds_a_cell, **kwargs)
    assert results[ENV_NAME]["warehouse"]["vdn"] == other       # kept when this process wrote its cell
    assert load_results(out) == results
    assert "1 already in" in logs[0] and not any("cell 1/2:" in line for line in logs)
    assert any(line.startswith("resuming from update 1") for line in logs)
    assert results[ENV_NAME]["simple_navigation"]["ippo"] == first[ENV_NAME]["simple_navigation"]["ippo"]
    runs = results[ENV_NAME]["simple_navigation"]["mappo"]
    assert sorted(runs) == ["run_0", "run_1"]
    steps = sorted(k for k in runs["run_0"] if k.startswith("step_"))
    assert len(steps) == 3 and [runs["run_0"][k]["step_count"] for k in sorted(steps)] == [1024, 2048, 3072]
    assert len(runs["run_1"]["step_2"]["reward"]) == 4 and len(runs["run_1"][ABSOLUTE]["reward"]) == 8
    assert set(runs["run_0"][ABSOLUTE]) >= {"reward", "steps", "collisions", "out_of_bounds", "best_test_return",
                                            "train_seconds", "wall_seconds", "env_steps"}
    # the resumed cell's wall time covers both invocations, not only the last one
    invocations = json.loads((out / "runs" / "simple_navigation" / "mappo" / benchmark.WALL_FILE).read_text())
    assert len(invocations["invocations"]) == 2 and min(invocations["invocations"]) > 0
    assert runs["run_0"][ABSOLUTE]["wall_seconds"] == [round(sum(invocations["invocations"]), 1)]
    assert runs["run_0"][ABSOLUTE]["device"] == [jax.devices()[0].device_kind]     # "cpu" here
    # not the recipe's settings (the report's files and curves: test_report_renders_tables_curves_and_improvement)
    assert "| simple_navigation | mappo† | 2 |" in report.report_markdown(results, reps=20)
    # each finished cell publishes its best seed's policy, which evaluate takes without the run folder
    from marbler_jax.numpy_policy import load_policy
    from marbler_jax_rl.evaluate import evaluate_policy
    from marbler_jax_rl.run import Run

    for algo in ("ippo", "mappo"):
        spec = load_policy(out / "policies" / f"simple_navigation-{algo}").spec
        assert spec["seed_index"] == Run.open(out / "runs" / "simple_navigation" / algo).best_seed()[0]
        assert spec["checkpoint"] == "best" and spec["algo"] == algo
    evaluated = evaluate_policy(out / "policies" / "simple_navigation-mappo", 4)
    assert (evaluated["scenario"], evaluated["algo"], evaluated["episodes"]) == ("simple_navigation", "mappo", 4)
    logs.clear()
    run_benchmark(out, **kwargs)                       # all done: nothing trains
    assert logs == [f"benchmark: 2 cell(s) for this process, 2 already in {out / 'results.json'}"]
    # another budget is another setting (as is an env override: test_env_and_hp_overrides_are_part_of_a_cells_settings):
    # the IPPO cell trains again, its earlier run folder set aside, not deleted
    logs.clear()
    plans = benchmark.plan_cells(out, **dict(plan_args, algos=["ippo"], total_steps=2 * 1024))
    assert [(p.status, p.replaces, p.updates) for p in plans] == [("restart", True, 2)]
    assert (out / "runs" / "simple_navigation" / "ippo").exists()          # planning moves nothing
    run = out / "runs" / "simple_navigation" / "ippo"
    with pytest.raises(ValueError, match=r"results.json holds simple_navigation/ippo made with other settings; this "
                                         r"run would replace it: give another --out \(e.g. for a smoke run\), or --force"):
        run_benchmark(out, **dict(kwargs, algos=["ippo"], total_steps=2 * 1024, eval_points=2))
    assert logs == [] and not (run.parent / "ippo.set-aside-1").exists()     # refused before anything moved
    again = run_benchmark(out, **dict(kwargs, algos=["ippo"], total_steps=2 * 1024, eval_points=2), force=True)
    assert logs[0].endswith("; 1 of its cells were made with other settings and train again")
    assert f"{run} holds a run with other settings: moved to {run}.set-aside-1" in logs
    assert (run.parent / "ippo.set-aside-1" / "params.npz").exists() and (run / "params.npz").exists()
    assert again[ENV_NAME]["simple_navigation"]["ippo"]["run_0"][ABSOLUTE]["env_steps"] == [2048]
    assert again[ENV_NAME]["simple_navigation"]["mappo"] == runs           # the other cell is kept


def test_env_and_hp_overrides_are_part_of_a_cells_settings():
    """``benchmark --set KEY=VALUE`` (and ``--hp``): the override replaces the recipe's env setting
    (hyperparameter) and changes the cell's digest, so a results cell made without it counts as made with
    other settings (and trains again)."""
    from marbler_jax_rl import recipes

    chosen = recipes.recipe("mappo")
    plain = benchmark.cell_settings(chosen, "predator_capture_prey")
    marbler_loop = benchmark.cell_settings(chosen, "predator_capture_prey", env_overrides={"control_period": 15})
    assert plain[0] == {"control_period": 1} and marbler_loop[0] == {"control_period": 15}
    # --protocol marbler replaces the recipe's loop instead of contradicting it
    protocol = benchmark.cell_settings(chosen, "predator_capture_prey", env_overrides={"protocol": "marbler"})
    assert protocol[0] == {"protocol": "marbler"}
    assert recipes.settings_digest(*protocol) != recipes.settings_digest(*plain)
    assert plain[1:] == marbler_loop[1:]
    assert recipes.settings_digest(*plain) == chosen.digest("predator_capture_prey")
    assert recipes.settings_digest(*marbler_loop) != recipes.settings_digest(*plain)
    assert benchmark.cell_settings(chosen, "warehouse", total_steps=5)[2] == 5
    # benchmark --hp: on top of the recipe of each algorithm that has the setting, and part of the digest
    wider = benchmark.cell_settings(chosen, "predator_capture_prey", hp_overrides={"hidden": 32, "td_lambda": 0.5})
    assert wider[1] == dict(plain[1], hidden=32) and recipes.settings_digest(*wider) != recipes.settings_digest(*plain)
    vdn = benchmark.cell_settings(recipes.recipe("vdn"), "warehouse", hp_overrides={"hidden": 64, "td_lambda": 0.5})
    assert vdn[1]["hidden"] == 64 and vdn[1]["td_lambda"] == 0.5
    assert chosen.config.hidden == 128 and "td_lambda" not in plain[1]     # the recipe itself is untouched
    with pytest.raises(ValueError, match=r"--hp td_lambda: none of the algorithms \['ippo', 'mappo'\] has this setting"):
        benchmark.check_hp_overrides({"td_lambda": 0.5}, ["mappo", "ippo"])
    for name, option in (("learner_devices", "--devices"), ("total_timesteps", "--total-steps")):
        with pytest.raises(ValueError, match=f"--hp {name}: set it with {option}"):
            benchmark.check_hp_overrides({name: 2}, ["vdn"])


def test_the_report_counts_the_recipe_in_either_protocol_as_the_recipe():
    """A cell of ``benchmark --protocol marbler`` is the current recipe in MARBLER's protocol, not a cell made
    with other settings (no †); a ``--set`` override still is."""
    from marbler_jax_rl import recipes
    from marbler_jax_rl.report import off_recipe

    chosen = recipes.recipe("vdn")

    def cell(**env_overrides):
        digest = recipes.settings_digest(*benchmark.cell_settings(chosen, "arctic_transport", env_overrides=env_overrides))
        return {"run_0": {benchmark.ABSOLUTE: {"recipe": [digest]}}}

    assert not off_recipe("arctic_transport", "vdn", cell())
    assert not off_recipe("arctic_transport", "vdn", cell(protocol="marbler"))
    assert not off_recipe("arctic_transport", "vdn", cell(protocol="robots"))
    assert off_recipe("arctic_transport", "vdn", cell(control_period=15))
    assert off_recipe("arctic_transport", "vdn", cell(protocol="marbler", control_period=1))


def test_benchmark_rejects_bad_settings(tmp_path):
    with pytest.raises(ValueError, match="seeds must be an integer >= 1, got 0"):
        run_benchmark(tmp_path, seeds=0)
    with pytest.raises(ValueError, match="total_steps must be >= 1"):
        run_benchmark(tmp_path, total_steps=-5)
    with pytest.raises(ValueError, match="test_episodes must be an integer >= 1, got 0"):   # the dry run's plan too
        benchmark.plan_cells(tmp_path, test_episodes=0)
    with pytest.raises(ValueError, match="seeds must be an integer >= 1, got True"):
        benchmark.plan_cells(tmp_path, seeds=True)
    with pytest.raises(ValueError, match=r"control_period must be a positive integer, got 0"):
        run_benchmark(tmp_path / "bad", scenarios=["warehouse"], env_overrides={"control_period": 0})
    assert not (tmp_path / "bad").exists()
    assert benchmark.results_name(1, 3) == "results-p1.json" and benchmark.results_name() == "results.json"


@pytest.mark.slow
def test_two_processes_share_the_grid_through_jax_distributed(tmp_path):
    """Two local processes join JAX's distributed runtime; each trains its own cell and writes its own
    results file, and ``report`` merges them."""
    import socket
    import subprocess
    import sys

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = tmp_path / "bench"
    procs = [subprocess.Popen([sys.executable, "-m", "marbler_jax_rl", "benchmark", "--algos", "ippo", "mappo",
                               "--scenarios", "simple", "--seeds", "1", "--total-steps", "2048", "--eval-points", "2",
                               "--test-episodes", "2", "--absolute-factor", "2", "--out", str(out), "--no-progress",
                               "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2", "--process-id", str(i)])
             for i in range(2)]
    assert [p.wait(timeout=900) for p in procs] == [0, 0]
    assert sorted(p.name for p in out.glob("results*.json")) == ["results-p0.json", "results-p1.json"]
    assert finished_cells(load_results(out)) == {("simple_navigation", "ippo"), ("simple_navigation", "mappo")}
    # --total-steps is not the recipe's budget: the merged report marks the cell †
    assert "| simple_navigation | mappo† | 1 |" in report.write_report(out, reps=20)[0].read_text()


def test_shard_flag_is_checked():
    from marbler_jax_rl.cli import _parse_shard, _without_options

    assert _without_options(["benchmark", "--coordinator", "h:1", "--process-id=1", "--seeds", "2"],
                            {"--coordinator", "--process-id"}) == ["benchmark", "--seeds", "2"]
    assert _parse_shard("1/3") == (1, 3) and _parse_shard(None) == (0, 1)
    for bad in ("3/3", "a/b", "1"):
        with pytest.raises(ValueError, match="--shard"):
            _parse_shard(bad)


def test_shortfalls_show_what_a_cell_misses_and_how_its_seeds_trained():
    # PCP VDN's paper reward is 33.25: the best seed (best test 33.0) scores 32.5 and collides in 2 % of episodes
    runs = _runs([[32.0, 33.0], [30.0, 31.0]], best_test=[33.0, 31.0], steps=(100, 200, 300, 400))
    runs["run_0"][ABSOLUTE]["collisions"] = [0.0, 4.0]             # % per episode: 2 % of the best seed's
    runs["run_1"]["step_1"]["reward"] = [40.0, 40.0]              # its best test came at 200 of 400 steps
    runs["run_1"]["step_2"]["reward"] = [31.5, 31.5]              # and its last quarter tests below the one before
    table = report.shortfall_table({ENV_NAME: {"predator_capture_prey": {"vdn": runs}}})
    assert table.startswith("### Cells short of the paper")
    row = next(line for line in table.splitlines() if line.startswith("| predator_capture_prey | vdn† |"))  # no recipe
    assert "| reward 32.50 < 33.25; collisions 2.00 > 1 |" in row
    # last-quarter gain: run_0's tests rise 24.375 -> 32.5 (300 -> 400 steps), run_1's fall 31.5 -> 30.5
    assert "| 32.50, 30.50 | 32.50 (0.0M), 40.00 (0.0M) | +8.12, -1.00 |" in row
    one_test = _runs([[30.0, 31.0]], steps=(100,))               # no quarter before the last: no gain to show
    table = report.shortfall_table({ENV_NAME: {"predator_capture_prey": {"vdn": one_test}}})
    assert "| 30.50 | 30.50 (0.0M) | — |" in table
    reaching = _runs([[34.0, 35.0]], steps=(100, 200))
    assert report.shortfall_table({ENV_NAME: {"predator_capture_prey": {"vdn": reaching}}}) is None


def test_curve_titles_mention_the_papers_line_only_where_the_paper_has_the_scenario():
    assert report.curve_title("warehouse") == "warehouse (dotted: the paper's reward, same colour)"
    assert report.curve_title("discovery") == "discovery"
