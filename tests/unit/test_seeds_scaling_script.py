"""benchmarks/seeds_scaling.py without training: bad arguments get a message, the plan always holds one SB3
process, the processes share the cores, and a measurement combines its processes' windows as its docstring says."""

import dataclasses
import importlib.util
import json
import sys
from pathlib import Path

import pytest
import torch as th

_PATH = Path(__file__).resolve().parents[2] / "benchmarks" / "seeds_scaling.py"


@pytest.fixture(scope="module")
def scaling():
    spec = importlib.util.spec_from_file_location("seeds_scaling", _PATH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclass looks its module up while it is built
    sys.path.insert(0, str(_PATH.parent))  # as when it runs as a script: it imports throughput.py beside it
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        del sys.modules[spec.name]
        sys.path.remove(str(_PATH.parent))


_BAD = [
    (["--seeds", "0", "2"], "each N must be at least 1"),
    (["--seeds", "2", "2"], "an N is given twice"),
    (["--env", "Hopper-v0"], "no gymnasium environment 'Hopper-v0'"),
    (["--env", "CartPole-v1"], "continuous (Box) actions"),
    (["--steps", "0"], "--steps must be at least 1"),
    (["--warmup", "0"], "--warmup must be at least 1"),
    (["--modes", "lone"], "invalid choice: 'lone'"),
    (["--learning-starts", "-1"], "--learning-starts must be at least 0"),
    (["--td3x", "cuda_graph"], "KEY=VALUE pairs"),
    (["--td3x", "cuda_graf=true"], "TD3X has no argument cuda_graf"),
    (["--td3x", "tau=0.01"], "tau is the benchmark's"),
    (["--td3x", "batch_size=64"], "batch_size is the benchmark's, the same for every model (--batch-size)"),
]
if not th.cuda.is_available():
    _BAD.append((["--device", "cuda"], "torch sees no CUDA device here"))  # SB3's get_device would fall back to CPU


@pytest.mark.parametrize("argv, message", _BAD)
def test_bad_arguments_get_a_message_not_a_traceback(scaling, capsys, argv, message):
    with pytest.raises(SystemExit) as exit_info:
        scaling.parse_arguments(argv)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_the_defaults_are_the_issues_cpu_setting(scaling):
    args = scaling.parse_arguments(["--modes", "batched", "batched", "sb3_procs"])
    assert args.seeds == [1, 2, 4, 8] and args.net == [400, 300] and args.batch_size == 100
    assert args.modes == ["batched", "sb3_procs"]
    assert args.device in ("cpu", "cuda")  # "auto" resolved, as SB3 resolves it


def test_one_sb3_process_is_always_measured_first_when_the_plan_lacks_it(scaling):
    assert scaling.plan(["batched", "td3x_procs"], [2, 4]) == [
        ("sb3_procs", 1),
        ("batched", 2),
        ("td3x_procs", 2),
        ("batched", 4),
        ("td3x_procs", 4),
    ]
    full = scaling.plan(list(scaling.MODES), [1, 16])
    assert full.count(("sb3_procs", 1)) == 1 and full[: len(scaling.MODES)] == [(mode, 1) for mode in scaling.MODES]


@pytest.mark.parametrize(
    "mode, n_seeds, cores, threads",
    [("batched", 8, 2, 2), ("td3x_procs", 1, 2, 2), ("td3x_procs", 2, 2, 1), ("sb3_procs", 8, 2, 1), ("sb3_procs", 4, 16, 4)],
)
def test_the_batch_gets_every_core_and_the_processes_share_them(scaling, mode, n_seeds, cores, threads):
    assert scaling.threads_for(mode, n_seeds, cores) == threads


def test_a_measurement_sums_its_processes_rates_and_reports_the_overlap_of_their_windows(scaling):
    records = [
        {"seeds": [0], "steps": 100, "seconds": 10.0, "steps_per_s": 10.0, "start": 0.0, "end": 10.0, "update_path": "mlp"},
        {"seeds": [1], "steps": 100, "seconds": 20.0, "steps_per_s": 5.0, "start": 0.5, "end": 20.5, "update_path": "mlp"},
    ]
    m = scaling.combine("td3x_procs", 2, 1, records)
    assert m["seed_steps_per_s"] == 15.0
    assert m["seed_steps_per_s_over_span"] == pytest.approx(200 / 20.5)
    assert m["overlap"] == pytest.approx(9.5 / 20.5)
    assert m["update_path"] == "mlp" and m["processes"] == 2


def test_ratios_are_taken_at_the_same_n_and_against_one_sb3_process(scaling):
    measurements = [
        {"mode": mode, "n_seeds": n, "processes": 1, "threads_per_process": 2, "seed_steps_per_s": rate, "update_path": None}
        for mode, n, rate in [("sb3_procs", 1, 100.0), ("batched", 1, 110.0), ("batched", 4, 600.0), ("td3x_procs", 4, 400.0)]
    ]
    rows = scaling.summarize(measurements + [{**measurements[2], "seed_steps_per_s": 800.0}])  # a second repeat
    assert rows[("batched", 4)]["seed_steps_per_s"] == 700.0  # the median of the repeats
    assert scaling.ratios(rows, [1, 4]) == [
        {"n_seeds": 1, "mode": "batched", "batched_over_td3x_procs": None, "batched_over_sb3_procs": 1.1,
         "batched_over_one_sb3_process": 1.1},
        {"n_seeds": 4, "mode": "batched", "batched_over_td3x_procs": 1.75, "batched_over_sb3_procs": None,
         "batched_over_one_sb3_process": 7.0},
    ]


def test_one_batch_per_core_splits_the_seeds_evenly(scaling):
    assert scaling.seed_groups("batched_per_core", 8, 2) == [[0, 2, 4, 6], [1, 3, 5, 7]]
    assert scaling.seed_groups("batched_per_core", 1, 2) == [[0]]
    assert scaling.seed_groups("batched", 4, 2) == [[0, 1, 2, 3]]
    assert scaling.seed_groups("td3x_procs", 3, 2) == [[0], [1], [2]]


def test_a_measurement_under_mps_is_the_same_way_of_training_labelled(scaling):
    assert scaling.base_mode("td3x_procs+mps") == "td3x_procs" and scaling.base_mode("batched") == "batched"
    assert scaling.seed_groups("td3x_procs+mps", 4, 2) == scaling.seed_groups("td3x_procs", 4, 2) == [[0], [1], [2], [3]]
    assert scaling.threads_for("sbx_procs+mps", 2, 2) == scaling.threads_for("sbx_procs", 2, 2) == 1
    assert "sbx_procs" not in scaling.parse_arguments([]).modes  # SBX only when asked (an optional dependency)


def test_td3x_arguments_reach_td3x_models_only(scaling):
    """``--td3x KEY=VALUE``: parsed into TD3X's keyword arguments, given to its models (lone and batched), never to
    SB3's ``TD3``, which would refuse them or train something else under the same label."""
    from stable_baselines3 import TD3

    from sb3_td3x import TD3X

    args = scaling.parse_arguments(["--env", "Pendulum-v1", "--td3x", "compile_update=false", "cuda_graph=false"])
    assert args.td3x_kwargs == {"compile_update": False, "cuda_graph": False}
    config = scaling.Config("Pendulum-v1", 32, (16,), 1_000, 100, 10, 10, "cpu", td3x_kwargs=tuple(args.td3x_kwargs.items()))
    td3x = scaling.make_model(TD3X, config, 0)
    assert td3x.compile_update is False and td3x.cuda_graph_request is False
    assert isinstance(scaling.make_model(TD3, config, 0), TD3)  # SB3's TD3 takes no compile_update: not given it
    assert scaling.make_model(TD3X, dataclasses.replace(config, td3x_kwargs=()), 0).compile_update is None


def test_the_json_holds_each_measurement_as_it_ends(scaling, tmp_path, monkeypatch):
    """A run cut by a time limit (the GPU sessions' calls) keeps what it measured: ``--json`` is written after each
    measurement, marked incomplete until the plan ends, and replaced whole (no half-written file)."""
    out = tmp_path / "seeds.json"
    seen = []

    def fake_measure(config, mode, n_seeds, threads, total_threads):  # the bookkeeping only: no training here
        if len(seen) == 2:
            raise KeyboardInterrupt  # the time limit's signal, during the third measurement
        seen.append(mode)
        record = {"seeds": [0], "steps": 10, "seconds": 1.0, "steps_per_s": 10.0 * len(seen), "start": 0.0, "end": 1.0,
                  "update_path": None}
        return scaling.combine(mode, n_seeds, threads, [record])

    monkeypatch.setattr(scaling, "measure", fake_measure)
    argv = ["--env", "Pendulum-v1", "--seeds", "1", "--modes", "td3x_procs", "batched", "--json", str(out)]
    with pytest.raises(KeyboardInterrupt):
        scaling.main(argv)
    record = json.loads(out.read_text())
    assert record["complete"] is False and [m["mode"] for m in record["measurements"]] == ["sb3_procs", "td3x_procs"]
    assert {row["mode"]: row["ratio_to_one_sb3_process"] for row in record["summary"]} == {"sb3_procs": 1.0, "td3x_procs": 2.0}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seeds.json"]

    seen.clear()
    monkeypatch.setattr(scaling, "measure", lambda config, mode, n, *rest: scaling.combine(mode, n, 1, [
        {"seeds": [0], "steps": 10, "seconds": 1.0, "steps_per_s": 5.0, "start": 0.0, "end": 1.0, "update_path": None}]))
    scaling.main(argv)  # the whole plan
    record = json.loads(out.read_text())
    assert record["complete"] is True and [m["mode"] for m in record["measurements"]] == ["sb3_procs", "td3x_procs", "batched"]
