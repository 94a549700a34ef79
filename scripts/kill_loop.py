"""Kill a run with SIGKILL at random moments, resume it each time, and check it ends as a run never killed.

    python scripts/kill_loop.py --kills 20 --work /tmp/kill_loop [run.py overrides ...]

Runs ``run.py`` once without interruption (the reference), then the same run again, killed ``--kills`` times at
random moments (checkpoints every ``checkpoint.freq`` steps, 25 by default, so kills land in saves as well as in
training) and resumed with ``resume=`` after each kill until it finishes. Exits 0 when the final weights,
optimizer states and evaluations (every column but the wall time) are bit-identical to the reference's, 1 otherwise,
printing what differs.
"""

from __future__ import annotations

import argparse
import csv
import random
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
RUN = ["debug=smoke", "torch_threads=1", "logger=none", "progress_bar=false", "checkpoint.freq=25", "checkpoint.save_best=false"]


def run_py(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "run.py", *args], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )


def tensors(run_dir: Path) -> dict[str, torch.Tensor]:
    """Every tensor of the final checkpoint's ``model.zip``: the networks and the optimizers' states."""
    found = {}
    with zipfile.ZipFile(run_dir / "checkpoints" / "last" / "model.zip") as archive:
        for name in archive.namelist():
            if name.endswith(".pth"):
                with archive.open(name) as file:
                    state = torch.load(file, map_location="cpu", weights_only=False)
                for key, value in _flat(state, name):
                    found[key] = value
    return found


def _flat(value: object, prefix: str):
    if isinstance(value, torch.Tensor):
        yield prefix, value
    elif isinstance(value, dict):
        for key, item in value.items():
            yield from _flat(item, f"{prefix}/{key}")
    elif isinstance(value, (list, tuple)):
        for index, item in enumerate(value):
            yield from _flat(item, f"{prefix}/{index}")


def evaluations(run_dir: Path) -> list[dict[str, str]]:
    with open(run_dir / "evaluations.csv") as file:
        return [{k: v for k, v in row.items() if k != "wall_time"} for row in csv.DictReader(file)]


def differences(reference: Path, killed: Path) -> list[str]:
    problems = []
    if evaluations(reference) != evaluations(killed):
        problems.append(f"evaluations differ:\n{evaluations(reference)}\n{evaluations(killed)}")
    ref, got = tensors(reference), tensors(killed)
    if ref.keys() != got.keys():
        problems.append(f"different tensors: {sorted(ref.keys() ^ got.keys())}")
    for key in sorted(ref.keys() & got.keys()):
        if not torch.equal(ref[key], got[key]):
            problems.append(f"{key}: max difference {(ref[key].double() - got[key].double()).abs().max().item()}")
    return problems


def kill_at_random_moment(process: subprocess.Popen, provenance: Path, rng: random.Random) -> None:
    """SIGKILL ``process`` at a random moment: one kill in four while it starts (loading the checkpoint), the others
    within half a second of training (the run writes a provenance line just before it trains)."""
    sessions = _lines(provenance)
    if rng.random() < 0.25:
        deadline = time.monotonic() + rng.uniform(0.5, 3.0)
    else:
        while _lines(provenance) == sessions and process.poll() is None:
            time.sleep(0.01)
        deadline = time.monotonic() + rng.uniform(0.0, 0.5)
    while time.monotonic() < deadline and process.poll() is None:
        time.sleep(0.005)
    if process.poll() is None:
        process.send_signal(signal.SIGKILL)
        process.wait()


def _lines(path: Path) -> int:
    try:
        return len(path.read_text().splitlines())
    except OSError:
        return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kills", type=int, default=20)
    parser.add_argument("--work", type=Path, required=True, help="a folder for the two runs (must not hold them yet)")
    parser.add_argument("--seed", type=int, default=0, help="of the moments of the kills")
    args, overrides = parser.parse_known_args()
    rng = random.Random(args.seed)
    reference, killed = args.work / "reference", args.work / "killed"
    command = RUN + overrides

    started = time.monotonic()
    process = run_py(*command, f"run_dir={reference}")
    output, _ = process.communicate()
    if process.returncode != 0:
        print(output[-3000:])
        return 1
    duration = time.monotonic() - started  # start-up and training: kills are spread over it
    print(f"reference: {duration:.1f} s")

    kills, resumes = 0, 0
    process = run_py(*command, f"run_dir={killed}")
    while True:
        if kills < args.kills:
            kill_at_random_moment(process, killed / "provenance.jsonl", rng)
            kills += process.returncode == -signal.SIGKILL
        output, _ = process.communicate()
        if process.returncode == 0:
            break
        if process.returncode != -signal.SIGKILL:
            print(output[-3000:])
            print(f"a resumed run failed with status {process.returncode}")
            return 1
        if not any((killed / "checkpoints").glob("last*/meta.json")):
            # Killed before its first checkpoint: nothing to resume; start again in a fresh folder, as a user would.
            subprocess.run(["rm", "-rf", str(killed)], check=True)
            process = run_py(*command, f"run_dir={killed}")
        else:
            resumes += 1
            process = run_py(f"resume={killed}", "progress_bar=false")
    print(f"{kills} kills, {resumes} resumes")
    problems = differences(reference, killed)
    for problem in problems:
        print(problem)
    print("bit-identical to the run never killed" if not problems else "DIFFERENT from the run never killed")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
