"""scripts/results.sh and scripts/publish_results.sh: the results pages' runs, built over several sittings."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]


def results_sh(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    env = {
        **os.environ,
        "JOBS": "2",
        "RESULTS_DIR": str(tmp_path / "runs"),
        "RUN_OVERRIDES": "debug=smoke eval.freq=300 logger=none",
    }
    venv = REPO / ".venv"
    if (venv / "bin" / "activate").exists():
        # As from a new shell: no interpreter named and the venv off PATH; the script activates the project's venv.
        env["PATH"] = os.pathsep.join(p for p in env["PATH"].split(os.pathsep) if not p.startswith(str(venv)))
        env.pop("VIRTUAL_ENV", None)
        env.pop("PYTHON", None)
    else:
        env["PYTHON"] = sys.executable
    return subprocess.run(
        ["bash", str(REPO / "scripts" / "results.sh"), *args], cwd=REPO, env=env, capture_output=True, text=True, timeout=600
    )


def final_step(run_dir: Path) -> int:
    return int(pd.read_csv(run_dir / "evaluations.csv")["timesteps"].iloc[-1])


HOPPER_JOBS = ["hopper:td3:0", "hopper:td3:1", "hopper:sb3_td3:0", "hopper:sb3_td3:1"]


@pytest.fixture(scope="module")
def hopper_runs(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    """``results.sh 600`` of two seeds of TD3X and of SB3's TD3 on Hopper, two runs at a time, made once for the tests
    of this file (each works on a copy of ``<folder>/runs``): the folder and the script's output."""
    folder = tmp_path_factory.mktemp("results")
    done = results_sh(folder, "600", *HOPPER_JOBS)
    assert done.returncode == 0, done.stdout + done.stderr
    return folder, done


def copy_runs(hopper_runs: tuple[Path, subprocess.CompletedProcess], tmp_path: Path) -> Path:
    shutil.copytree(hopper_runs[0] / "runs", tmp_path / "runs")
    return tmp_path / "runs"


def test_runs_start_skip_when_done_and_resume_to_more_steps(tmp_path, hopper_runs):
    made, done = hopper_runs
    for job in HOPPER_JOBS:
        env, algo, seed = job.split(":")
        run_dir = made / "runs" / env / algo / f"seed{seed}"
        assert f"starting: {run_dir}" in done.stdout and final_step(run_dir) == 600, done.stdout
    assert "stable_baselines3.TD3" in (made / "runs" / "hopper" / "sb3_td3" / "seed0" / "config.yaml").read_text()
    # JOBS=2 runs side by side share the cores
    threads = max(1, len(os.sched_getaffinity(0)) // 2)
    assert yaml.safe_load((made / "runs" / "hopper" / "td3" / "seed0" / "config.yaml").read_text())["torch_threads"] == threads

    td3x = copy_runs(hopper_runs, tmp_path) / "hopper" / "td3" / "seed0"  # resume= continues a run in the folder given
    again = results_sh(tmp_path, "600", "hopper:td3:0")
    assert again.returncode == 0 and f"done already: {td3x}" in again.stdout

    longer = results_sh(tmp_path, "900", "hopper:td3:0")
    assert longer.returncode == 0, longer.stdout + longer.stderr
    assert f"resuming: {td3x}" in longer.stdout and final_step(td3x) == 900
    sessions = [json.loads(line) for line in (td3x / "provenance.jsonl").read_text().splitlines()]
    assert [session["at_step"] for session in sessions] == [0, 600]

    shutil.rmtree(td3x / "checkpoints" / "last")  # only the checkpoint before it left (last.prev): still resumed
    older = results_sh(tmp_path, "1000", "hopper:td3:0")
    assert older.returncode == 0 and f"resuming: {td3x}" in older.stdout, older.stdout + older.stderr
    assert final_step(td3x) == 1000


def test_bad_arguments_are_refused_with_a_message(tmp_path):
    steps = results_sh(tmp_path, "lots", "pendulum:td3:0")
    assert steps.returncode == 2 and "STEPS must be a whole number" in steps.stderr
    job = results_sh(tmp_path, "600", "pendulum-td3-0")
    assert job.returncode != 0 and "is not env:algo:seed" in job.stderr
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").rglob("evaluations.csv"))
    # A run that fails says why on the script's own output (run.py's last line), not only "exit 2".
    failed = results_sh(tmp_path, "600", "pendulum:no_such_algo:0")
    assert failed.returncode != 0 and "there is no config 'no_such_algo'" in failed.stdout, failed.stdout


def test_a_run_that_never_checkpointed_is_moved_out_of_the_results_folder(tmp_path):
    # Records of a run killed before its first checkpoint: it cannot resume, and a new run may not start over them.
    # They are moved, never deleted, and out of the folder that the aggregation reads (where seed 5 would be twice).
    killed = tmp_path / "runs" / "hopper" / "no_such_algo" / "seed5"
    killed.mkdir(parents=True)
    (killed / "config.yaml").write_text("seed: 5\n")
    (killed / "evaluations.csv").write_text("timesteps,mean_return\n300,1.0\n")
    out = results_sh(tmp_path, "600", "hopper:no_such_algo:5")  # the run then fails at once: no such algo
    assert "there is no config 'no_such_algo'" in out.stdout, out.stdout + out.stderr
    (aside,) = (tmp_path / "runs.unfinished" / "hopper" / "no_such_algo").iterdir()
    assert aside.name.startswith("seed5-") and f"its records moved to {aside}" in out.stdout, out.stdout
    assert (aside / "evaluations.csv").read_text() == "timesteps,mean_return\n300,1.0\n"
    assert not list((tmp_path / "runs").rglob("evaluations.csv")) and not list((tmp_path / "runs").rglob("config.yaml"))


def test_a_run_in_progress_before_its_first_checkpoint_is_left_to_its_process(tmp_path):
    # The same command started twice: the second finds the first's records and no checkpoint yet. The folder's owner
    # holds its lock; the folder is neither moved nor started over.
    from sb3_td3x.experiment.run.lock import RunFolderLock

    running = tmp_path / "runs" / "hopper" / "no_such_algo" / "seed6"
    lock = RunFolderLock.acquire(running)
    try:
        (running / "evaluations.csv").write_text("timesteps,mean_return\n300,1.0\n")
        out = results_sh(tmp_path, "600", "hopper:no_such_algo:6")
    finally:
        lock.release()
    busy = f"busy, left as it is: The run folder {running} is in use by process {os.getpid()}"
    assert out.returncode != 0 and busy in out.stdout, out.stdout + out.stderr
    assert sorted(path.name for path in running.iterdir()) == [".lock", "evaluations.csv"]
    assert not (tmp_path / "runs.unfinished").exists()


def test_publish_copies_the_records_and_aggregates_them(tmp_path, hopper_runs):
    copy_runs(hopper_runs, tmp_path)
    # A seed still running (no summary.json yet): shown with its progress, not aggregated with the finished ones
    running = tmp_path / "runs" / "hopper" / "td3" / "seed2"
    running.mkdir()
    (running / "config.yaml").write_text((tmp_path / "runs" / "hopper" / "td3" / "seed0" / "config.yaml").read_text())
    pd.read_csv(tmp_path / "runs" / "hopper" / "td3" / "seed0" / "evaluations.csv").iloc[:1].to_csv(
        running / "evaluations.csv", index=False)
    docs = tmp_path / "docs"
    page = tmp_path / "results.md"
    page.write_text("# Results\n<!-- HOPPER_SB3 -->\n<!-- /HOPPER_SB3 -->\n<!-- ABLATION -->\nold\n<!-- /ABLATION -->\n"
                    "text\n<!-- MUJOCO -->\n<!-- /MUJOCO -->\n<!-- VALUE_BIAS -->\n<!-- /VALUE_BIAS -->\n")
    out = subprocess.run(
        ["bash", str(REPO / "scripts" / "publish_results.sh"), str(tmp_path / "runs")],
        cwd=tmp_path,  # the script works from the repository root whatever the caller's folder
        env={**os.environ, "PYTHON": sys.executable, "RESULTS_DOCS_DIR": str(docs), "RESULTS_PAGE": str(page)},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    for algo in ("td3", "sb3_td3"):
        for seed in (0, 1):
            assert sorted(path.name for path in (docs / "runs" / "hopper" / algo / f"seed{seed}").iterdir()) == [
                "config.yaml", "evaluations.csv", "provenance.jsonl", "summary.json",
            ]  # fmt: skip: the small records only, no checkpoints
    table = pd.read_csv(docs / "hopper_td3x_vs_sb3" / "aggregate.csv")
    assert sorted(table.algo) == ["sb3_td3", "td3"] and set(table.n_runs) == {2} and set(table.timesteps) == {600}
    assert (docs / "hopper_td3x_vs_sb3" / "aggregate_Hopper-v5.png").is_file()
    per_seed = pd.read_csv(docs / "hopper_td3x_vs_sb3" / "per_seed.csv")  # one row per run, the finals in long format
    assert sorted(zip(per_seed.algo, per_seed.seed)) == [("sb3_td3", 0), ("sb3_td3", 1), ("td3", 0), ("td3", 1)]
    for algo, finals in per_seed.groupby("algo")["final_return"]:
        assert finals.mean() == pytest.approx(table.set_index("algo").loc[algo, "final_mean"])
    assert not list(docs.rglob("*.md"))  # under docs/, a Markdown file would be a page of the site
    assert (docs / "hopper_ablation" / "aggregate.csv").is_file() and (docs / "td3x_mujoco" / "aggregate.csv").is_file()
    # The page's tables are rewritten from the aggregates and the runs' records, between their markers
    lines = page.read_text().splitlines()
    assert "old" not in lines and "text" in lines
    # TD3X against SB3: 5 seeds planned, then the difference of the finished ones from compare.csv
    td3x = next(line for line in lines if line.startswith("| TD3X (`td3`) |"))
    assert "| 0: 600, 1: 600, 2: 300 of 600, 3: not started, 4: not started | 600 |" in td3x, td3x
    assert next(line for line in lines if line.startswith("| SB3 `TD3`")).count("not started") == 3
    assert "| TD3X (`td3`) minus SB3 `TD3` (`sb3_td3`) (2 seeds against 2) |" in page.read_text()
    final = next(line for line in lines if line.startswith("| final return (600) |"))
    finals = table.set_index("algo")["final_mean"]
    assert float(final.split("|")[2].split()[0]) == pytest.approx(finals["td3"] - finals["sb3_td3"], abs=0.05)
    compared = pd.read_csv(docs / "hopper_td3x_vs_sb3" / "compare.csv")
    assert (compared.algo_a[0], compared.algo_b[0]) == ("sb3_td3", "td3")  # stored once, in name order; shown td3 first
    assert float(final.split("|")[3]) == pytest.approx(compared.final_p_value[0], abs=0.005)
    assert next(line for line in lines if line.startswith("| mean return over all ")).count("|") == 4
    td3 = next(line for line in lines if line.startswith("| TD3 (`td3`)"))
    assert "| 0: 600, 1: 600, 2: 300 of 600 | 600 |" in td3, td3
    assert next(line for line in lines if line.startswith("| DDPG")).count("not started") == 3
    hopper = next(line for line in lines if line.startswith("| Hopper-v5"))
    assert hopper.split("|")[3].strip() == "600" and hopper.split("|")[5].strip().count(",") == 1  # two seeds' finals
    assert "| Ant-v5 | 0: not started, 1: not started, 2: not started | | | | |" in lines
    # The overestimation table (the paper's Figure 1) from the value columns of the finished seeds
    values = pd.read_csv(docs / "value_bias" / "value_bias.csv")
    assert list(values.algo) == ["td3"] and values.n_runs[0] == 2 and values.timesteps[0] == 600
    assert (docs / "value_bias" / "value_bias_Hopper-v5.png").is_file()
    td3_values = next(line for line in lines if line.startswith("| Hopper-v5, TD3 (`td3`)"))
    cells = [cell.strip() for cell in td3_values.split("|")[1:-1]]
    assert cells[1] == "0: 600, 1: 600, 2: 300 of 600, 3: not started, 4: not started" and cells[2] == "600"  # 5 planned
    assert float(cells[5].split()[0]) == pytest.approx(values.overestimation[0], abs=0.05) and cells[7].startswith("0: ")
    assert next(line for line in lines if line.startswith("| Hopper-v5, DDPG")).count("not started") == 5


def test_publish_never_replaces_a_published_run_with_a_shorter_one(tmp_path, hopper_runs):
    """Local runs of 600 steps where the published record of the same folder reached more: nothing is copied."""
    copy_runs(hopper_runs, tmp_path)
    docs = tmp_path / "docs"
    published = docs / "runs" / "hopper" / "td3" / "seed0"
    published.mkdir(parents=True)
    longer = pd.read_csv(tmp_path / "runs" / "hopper" / "td3" / "seed0" / "evaluations.csv")
    longer.loc[len(longer)] = longer.iloc[-1].to_dict() | {"timesteps": 200_000}
    longer.to_csv(published / "evaluations.csv", index=False)
    before = (published / "evaluations.csv").read_bytes()
    out = subprocess.run(
        ["bash", str(REPO / "scripts" / "publish_results.sh"), str(tmp_path / "runs")],
        env={**os.environ, "PYTHON": sys.executable, "RESULTS_DOCS_DIR": str(docs), "RESULTS_PAGE": ""},
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert out.returncode == 2, out.stdout + out.stderr
    assert "replace published runs with shorter ones" in out.stderr and "600 steps, its published record 200,000" in out.stderr
    assert "Traceback" not in out.stderr
    assert (published / "evaluations.csv").read_bytes() == before
    assert sorted(path.name for path in published.iterdir()) == ["evaluations.csv"]


def test_results_tables_refuse_a_page_without_markers(tmp_path):
    page = tmp_path / "results.md"
    page.write_text("# Results\nno markers\n")
    out = subprocess.run([sys.executable, str(REPO / "scripts" / "results_tables.py"), "--docs-dir", str(tmp_path),
                          "--page", str(page)], capture_output=True, text=True)
    assert out.returncode == 2 and "has no <!-- HOPPER_SB3 -->" in out.stderr and "Traceback" not in out.stderr
    assert page.read_text() == "# Results\nno markers\n"


def test_a_group_published_from_runs_not_here_is_left_as_it_is(tmp_path):
    """Records of an earlier machine's runs are gone: the table and aggregate they made stay as published, rather
    than being rewritten as 'not started' beside the old numbers (found on the real page, 2026-11-23)."""
    group = tmp_path / "td3x_mujoco"
    group.mkdir()
    (group / "aggregate.csv").write_text("env_id,algo,n_runs,timesteps,final_mean\nAnt-v5,td3,1,200000,1427.5\n")
    (group / "per_seed.csv").write_text(
        "env_id,algo,seed,run_dir,timesteps,final_return\n"
        "Ant-v5,td3,0,/elsewhere/docs/assets/results/runs/ant/td3/seed0,200000,1427.5\n"
    )
    page = tmp_path / "results.md"
    page.write_text("<!-- HOPPER_SB3 -->\n<!-- /HOPPER_SB3 -->\n<!-- ABLATION -->\n<!-- /ABLATION -->\n"
                    "<!-- MUJOCO -->\nkept\n<!-- /MUJOCO -->\n<!-- VALUE_BIAS -->\n<!-- /VALUE_BIAS -->\n")
    script = [sys.executable, str(REPO / "scripts" / "results_tables.py"), "--docs-dir", str(tmp_path)]
    missing = subprocess.run([*script, "--missing-runs", "td3x_mujoco"], capture_output=True, text=True)
    assert missing.returncode == 3 and missing.stdout.split() == ["ant/td3/seed0"]
    out = subprocess.run([*script, "--page", str(page)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "table MUJOCO left as it is" in out.stderr and "ant/td3/seed0" in out.stderr
    assert "<!-- MUJOCO -->\nkept\n<!-- /MUJOCO -->" in page.read_text()  # untouched
    assert "| Hopper-v5, TD3 (`td3`) | 0: not started" in page.read_text()  # the others are filled
    # The folder made again by another run of the same seed (published where the first one's records never were):
    # still missing, said as such (found on the real page, 2026-11-28: the ablation's hopper/td3 seeds).
    record = tmp_path / "runs" / "ant" / "td3" / "seed0"
    record.mkdir(parents=True)
    (record / "evaluations.csv").write_text("timesteps,mean_return\n100000,900.0\n200000,2469.1\n")
    missing = subprocess.run([*script, "--missing-runs", "td3x_mujoco"], capture_output=True, text=True)
    assert missing.returncode == 3 and missing.stdout.splitlines() == ["ant/td3/seed0 (holds another run)"]
    # Once the records are back (the run's, gone on since: the return aggregated at 200k is still there), the group
    # is rewritten as usual.
    (record / "evaluations.csv").write_text("timesteps,mean_return\n100000,900.0\n200000,1427.5\n205000,1500.0\n")
    assert subprocess.run([*script, "--missing-runs", "td3x_mujoco"], capture_output=True).returncode == 0


def test_the_overestimation_table_is_followed_by_ddpg_minus_td3(tmp_path):
    """And by TD3 without clipped double-Q minus TD3, which value_bias_compare.csv holds as td3 minus td3_no_cdq
    (each pair once, in name order): turned round, signs and interval too."""
    (tmp_path / "value_bias").mkdir()
    (tmp_path / "value_bias" / "value_bias_compare.csv").write_text(
        "env_id,algo_a,algo_b,n_a,n_b,timesteps,n_evaluations,final_difference,final_ci_low,final_ci_high,final_p_value,"
        "curve_difference,curve_ci_low,curve_ci_high,curve_p_value\n"
        "Hopper-v5,ddpg,td3,5,4,200000,40,299.64,133.3,522.0,0.0079,258.7,202.1,343.9,0.0159\n"
        "Hopper-v5,td3,td3_no_cdq,6,4,200000,40,-170.1,-307.2,-33.7,0.019,-124.5,-197.8,-50.1,0.0096\n"
    )
    page = tmp_path / "results.md"
    page.write_text("<!-- HOPPER_SB3 -->\n<!-- /HOPPER_SB3 -->\n<!-- ABLATION -->\n<!-- /ABLATION -->\n"
                    "<!-- MUJOCO -->\n<!-- /MUJOCO -->\n<!-- VALUE_BIAS -->\n<!-- /VALUE_BIAS -->\n")
    out = subprocess.run([sys.executable, str(REPO / "scripts" / "results_tables.py"), "--docs-dir", str(tmp_path),
                          "--page", str(page)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    text = page.read_text()
    assert "| Hopper-v5: DDPG (`ddpg`) minus TD3 (`td3`) (5 seeds against 4) |" in text
    assert "| overestimation at the last step (200k) | +299.6 (+133.3 to +522.0) | 0.008 |" in text
    assert "| mean overestimation over all 40 evaluations | +258.7 (+202.1 to +343.9) | 0.016 |" in text
    no_cdq = text.split("TD3 without clipped double-Q (`td3_no_cdq`) minus TD3 (`td3`) (4 seeds against 6) |")[1]
    assert "| overestimation at the last step (200k) | +170.1 (+33.7 to +307.2) | 0.019 |" in no_cdq
    assert "| mean overestimation over all 40 evaluations | +124.5 (+50.1 to +197.8) | 0.010 |" in no_cdq
    assert "Walker2d-v5: DDPG" not in text  # no Walker2d runs compared: no table for it
    assert "minus SB3" not in text  # nor for TD3X against SB3
