"""Every ``python run.py``, ``python -m sb3_td3x.sweeps`` and ``bash scripts/results.sh`` command that the README and
the pages of docs/ show is one the program accepts, and where a page shows what run.py prints for one (a ``$ ``
prompt, then the output), run.py prints that.

The commands are read from the pages themselves: the lines of their code blocks and their inline code that run the
program (after ``VAR=value`` assignments, after ``&&``, or quoted as one word), a ``\\`` continuing a line onto the
next. A template with a placeholder (``<date>``, ``$(cat best_overrides.txt)``, ``...``) is no command and is left
out. The commands go through the program's own checks of a command line, in-process, so nothing trains and no
storage is opened: run.py's :func:`check_command_line` (the config composed as Hydra will, every override and group
choice checked, a user's class imported; for results.sh, each env:algo:seed job as the script starts it) and the
sweep's :func:`check_command` (its arguments, the sweep file, the trials' overrides, the launcher file). The errors
shown run ``run.py`` itself, side by side, so that everything it writes to the terminal is compared with the page.
"""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
from conftest import importable_from

from sb3_td3x.experiment.cli import EXIT_CONFIG_ERROR, check_command_line
from sb3_td3x.experiment.configs.schemas import CONF_DIR
from sb3_td3x.sweeps.cli import build_parser, check_command
from sb3_td3x.sweeps.results import TUNED_GROUP, tuned_config

REPO = Path(__file__).resolve().parents[2]
#: The pages a user reads. The performance log is left out: a record of commands as they were run at the time.
PAGES = [REPO / "README.md", *sorted(p for p in (REPO / "docs").glob("*.md") if p.name != "performance_log.md")]


@dataclass(frozen=True)
class Shown:
    page: str
    line: int
    program: tuple[str, ...]  #: ``python run.py``, ``python -m sb3_td3x.sweeps``
    args: tuple[str, ...]  #: what follows it
    output: str  #: what the page shows it printing ("" where it shows nothing)

    def __str__(self) -> str:
        return f"{self.page}:{self.line}: {shlex.join(self.program + self.args)}"


RUN_PY = ("python", "run.py")
SWEEP = ("python", "-m", "sb3_td3x.sweeps")
RESULTS = ("bash", "scripts/results.sh")


def _arguments(text: str, program: tuple[str, ...]) -> tuple[str, ...] | None:
    """The arguments given to ``program`` by ``text`` (a shell line, commands joined by ``&&``, ``;`` or ``&``, or a
    command quoted as one word, as ``sbatch --wrap "python run.py ..."`` takes it), None if it does not run it."""
    for part in re.split(r"&&|;|&", text.split(" #")[0]):
        try:
            words = shlex.split(part)
        except ValueError:
            continue
        while words and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*=\S*", words[0]):  # MUJOCO_GL=egl python run.py ...
            words = words[1:]
        if tuple(words[: len(program)]) == program:
            return tuple(words[len(program) :])
        for word in words[1:]:
            if word.startswith(" ".join(program) + " "):
                return _arguments(word, program)
    return None


def documented_commands(program: tuple[str, ...] = RUN_PY) -> list[Shown]:
    commands: list[Shown] = []
    for page in PAGES:
        text = page.read_text(encoding="utf-8")
        for block in re.finditer(r"^```[a-z]*\n(.*?)^```", text, flags=re.DOTALL | re.MULTILINE):
            first_line = text.count("\n", 0, block.start(1)) + 1
            lines = block.group(1).splitlines()
            i = 0
            while i < len(lines):
                start, prompt = i, lines[i].startswith("$ ")
                line = lines[i][2:] if prompt else lines[i]
                while line.rstrip().endswith("\\") and i + 1 < len(lines):
                    i += 1
                    line = line.rstrip()[:-1] + " " + lines[i].strip()
                output = []
                while prompt and i + 1 < len(lines) and not lines[i + 1].startswith("$ "):
                    i += 1
                    output.append(lines[i].strip())
                args = _arguments(line, program)
                if args is not None and not _is_template(line):
                    commands.append(Shown(page.name, first_line + start, program, args, " ".join(output)))
                i += 1
        for span in re.finditer(r"`(" + re.escape(" ".join(program)) + r"[^`]*)`", text):
            args = _arguments(span.group(1), program)
            if args is not None and not _is_template(span.group(1)):
                commands.append(Shown(page.name, text.count("\n", 0, span.start()) + 1, program, args, ""))
    return commands


def _is_template(line: str) -> bool:
    return bool(re.search(r"<[^>]*>|\$\(|\.\.\.", line.split("#")[0]))


COMMANDS = documented_commands()
ACCEPTED = [c for c in COMMANDS if not c.output.startswith("Error:")]
REFUSED = [c for c in COMMANDS if c.output.startswith("Error:")]
#: The sweep's commands (the program named alone, in a sentence, and ``--help`` left out).
SWEEPS = [c for c in documented_commands(SWEEP) if c.args and "--help" not in c.args]
#: The commands that train the runs behind docs/results.md: STEPS, then env:algo:seed jobs.
RESULTS_RUNS = documented_commands(RESULTS)


def test_the_pages_show_commands():
    """The reading above finds what the pages hold (a change of their layout must not leave this test with nothing)."""
    assert len(ACCEPTED) >= 30 and len(REFUSED) >= 4 and len(SWEEPS) >= 10 and len(RESULTS_RUNS) >= 8
    assert {"README.md", "experiments.md", "cluster.md", "seeds.md", "sweeps.md", "variants.md"} <= {
        c.page for c in ACCEPTED
    }
    assert any(c.page == "cluster.md" and c.args == ("algo=td3", "env=ant") for c in ACCEPTED)  # sbatch --wrap "..."


@pytest.fixture
def where_a_user_types_them(tmp_path, monkeypatch):
    """A folder to start run.py in, holding what the pages tell the user to make first: ``mymodule.py`` of the page on
    one's own class (the page's code block itself), and a sweep's study folder with its ``tuned/best.yaml``."""
    experiments = (REPO / "docs" / "experiments.md").read_text(encoding="utf-8")
    (mymodule,) = re.findall(r"```python\n(# mymodule\.py.*?)```", experiments, flags=re.DOTALL)
    (tmp_path / "mymodule.py").write_text(mymodule)
    importable_from(tmp_path, monkeypatch)
    study = tmp_path / "runs" / "sweeps" / "td3x-pendulum"
    (study / TUNED_GROUP).mkdir(parents=True)
    (study / TUNED_GROUP / "best.yaml").write_text(tuned_config(["algo.tau=0.01", "algo.batch_size=128"], CONF_DIR))
    monkeypatch.chdir(tmp_path)
    return tmp_path


@pytest.mark.parametrize("command", ACCEPTED, ids=str)
def test_a_documented_command_is_one_run_py_accepts(command, where_a_user_types_them):
    check_command_line(list(command.args), CONF_DIR)  # a refused command exits (SystemExit) with its message
    assert not (where_a_user_types_them / "outputs").exists()  # checked, nothing written


def test_the_errors_shown_are_what_run_py_prints(tmp_path):
    """Each refused command's whole terminal output: exit status 2, one line on stderr that reads as the page shows
    it (up to its ``...``), nothing on stdout."""
    processes = {
        command: subprocess.Popen(
            [sys.executable, str(REPO / "run.py"), *command.args], cwd=REPO, text=True,
            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        )
        for command in REFUSED
    }
    for command, process in processes.items():
        stdout, stderr = process.communicate(timeout=300)
        assert process.returncode == EXIT_CONFIG_ERROR, (str(command), stderr[-2000:])
        assert stdout == "" and stderr.count("\n") == 1, (str(command), stdout, stderr)
        shown = command.output.split("...")[0].strip()
        assert " ".join(stderr.split()).startswith(shown), (str(command), shown, stderr)


@pytest.mark.parametrize("command", SWEEPS, ids=str)
def test_a_documented_sweep_command_is_one_the_sweep_accepts(command, tmp_path, monkeypatch):
    monkeypatch.chdir(REPO)  # the pages' sweep files and launcher files are named from the repository's root
    args = build_parser().parse_intermixed_args([*command.args, "--output-dir", str(tmp_path)])
    check_command(args)  # a refused command raises SweepError with its message
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("command", RESULTS_RUNS, ids=str)
def test_a_documented_results_command_starts_runs_run_py_accepts(command, tmp_path):
    """Each job (bash's brace expansion applied, as the shell does) as ``scripts/results.sh`` starts it: one seed of
    each environment and algorithm (the seed changes nothing that is checked)."""
    expanded = subprocess.run(
        ["bash", "-c", 'printf "%s\\n" ' + " ".join(command.args)], check=True, capture_output=True, text=True
    ).stdout.split()
    steps, *jobs = expanded
    assert steps.isdigit() and jobs and all(re.fullmatch(r"\w+:\w+:\d+", job) for job in jobs), expanded
    first_seed = {tuple(job.split(":")[:2]): job.split(":")[2] for job in reversed(jobs)}
    for (env, algo), seed in first_seed.items():
        run_dir = tmp_path / env / algo / f"seed{seed}"
        check_command_line(
            [f"env={env}", f"algo={algo}", f"seed={seed}", "torch_threads=1", f"total_timesteps={steps}",
             "checkpoint.freq=25000", f"run_dir={run_dir}", "progress_bar=false"],
            CONF_DIR,
        )
