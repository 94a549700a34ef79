"""``python -m sb3_td3x.sweeps``: run (or continue) an Optuna search over the configs ``run.py`` trains."""

from __future__ import annotations

import argparse
import logging
import os
import re
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from sb3_td3x.common.redaction import redact, redact_log_records
from sb3_td3x.experiment import stops
from sb3_td3x.sweeps.errors import SweepError

if TYPE_CHECKING:
    from sb3_td3x.sweeps.spec import SweepSpec

logger = logging.getLogger("sb3_td3x.sweeps")

EXAMPLES = """\
examples:
  python -m sb3_td3x.sweeps sweeps/pendulum.yaml                      # SQLite in runs/sweeps/td3x-pendulum/
  python -m sb3_td3x.sweeps sweeps/pendulum.yaml                      # again: continues the same study
  python -m sb3_td3x.sweeps sweeps/pendulum.yaml --n-trials 60        # grow it to 60 trials
  python -m sb3_td3x.sweeps sweeps/hopper.yaml device=cpu --storage postgresql://td3x:td3x@db-host/td3x
  python -m sb3_td3x.sweeps sweeps/hopper.yaml --storage postgresql://... --launcher sweeps/launcher/slurm.yaml --workers 16
  python -m sb3_td3x.sweeps sweeps/pendulum.yaml --report             # write the results files only

Every worker pointed at the same --storage and study name shares one budget of --n-trials trials.
Results (in --output-dir/<study>): summary.txt, trials.csv, best_overrides.txt, tuned/best.yaml, plots/*.png.
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m sb3_td3x.sweeps",
        description="Tune TD3X with Optuna: each trial composes conf/ like run.py, reports its periodic "
        "evaluations, and is pruned when the pruner says so. Studies persist in the storage; run the same command "
        "again (or on more machines) to continue.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("sweep_file", type=Path, help="search-space file, e.g. sweeps/pendulum.yaml")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for every trial, after the file's (e.g. device=cpu)")
    parser.add_argument("--study-name", help="default: the file's study_name")
    parser.add_argument(
        "--storage",
        help="sqlite:///path.db, postgresql://user:password@host:5432/db, any SQLAlchemy URL, or a journal file "
        "journal:path.log; default: the file's storage, else sqlite:///<output-dir>/<study>/optuna.db",
    )
    parser.add_argument(
        "--n-trials", type=int, help="trials the study holds in total, shared by all workers (default: the file's)"
    )
    parser.add_argument(
        "--output-dir", type=Path, default=Path("runs/sweeps"), help="study folders go here (default: %(default)s)"
    )
    parser.add_argument("--config-dir", type=Path, help="the conf/ folder run.py composes (default: the repository's conf/)")
    parser.add_argument(
        "--heartbeat-interval",
        type=int,
        default=60,
        help="seconds between heartbeats of a running trial (default: %(default)s)",
    )
    parser.add_argument(
        "--grace-period",
        type=int,
        help="seconds without heartbeat before a trial is marked FAIL (default: twice the interval)",
    )
    parser.add_argument(
        "--retry-stale", type=int, default=0, help="queue a dead worker's trial again up to N times (default: %(default)s)"
    )
    parser.add_argument(
        "--max-consecutive-failures",
        type=int,
        default=5,
        help="stop a worker after N crashed trials in a row (default: %(default)s)",
    )
    parser.add_argument("--report", action="store_true", help="only write the results of the study in the storage")
    parser.add_argument("--launcher", type=Path, help="submit --workers jobs with this launcher file (sweeps/launcher/*.yaml)")
    parser.add_argument(
        "--workers", type=int, default=1, help="number of worker jobs to submit with --launcher (default: %(default)s)"
    )
    parser.add_argument("--wait", action="store_true", help="with --launcher: wait for the jobs and report their exit")
    parser.add_argument("-q", "--quiet", action="store_true", help="log only warnings")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_intermixed_args(argv)
    _setup_logging(args.quiet)
    try:
        return _run(args)
    except SweepError as err:
        print(redact(f"error: {err}"), file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # before the worker loop, which holds signals (sb3_td3x.experiment.stops.HeldSignals)
        print(
            "Interrupted before this worker started a trial: no trial of it is running. Run the same command to continue.",
            file=sys.stderr,
        )
        return 130


def check_arguments(args: argparse.Namespace) -> None:
    """Refuse a value no sweep can run with, before anything is opened or written."""
    at_least = {
        "--n-trials": (args.n_trials, 1),
        "--heartbeat-interval": (args.heartbeat_interval, 1),
        "--retry-stale": (args.retry_stale, 0),
        "--max-consecutive-failures": (args.max_consecutive_failures, 1),
        "--workers": (args.workers, 1),
    }
    for option, (value, lowest) in at_least.items():
        if value is not None and value < lowest:
            raise SweepError(f"{option} must be at least {lowest}, got {value}; see python -m sb3_td3x.sweeps --help")
    if args.grace_period is not None and args.grace_period <= args.heartbeat_interval:
        raise SweepError(
            f"--grace-period ({args.grace_period}s) must be longer than --heartbeat-interval "
            f"({args.heartbeat_interval}s): a trial is marked FAIL after a grace period without a heartbeat, so a "
            f"shorter one would fail healthy trials between two beats. Leave it out (twice the interval) or pass "
            f"--grace-period {2 * args.heartbeat_interval} or more."
        )
    if args.study_name is not None and not re.fullmatch(r"[\w.\-]+", args.study_name):
        raise SweepError(f"--study-name {args.study_name!r} may hold only letters, digits, '.', '_' and '-'")
    if args.output_dir.exists() and not args.output_dir.is_dir():
        raise SweepError(f"--output-dir {args.output_dir} is a file; pass a folder for the study folders")


def check_command(args: argparse.Namespace) -> tuple[SweepSpec, Path]:
    """The sweep a command line runs and the config folder its trials compose from, checked before a storage is opened
    or anything is written: the arguments, the sweep file, that a trial's overrides compose, ``--launcher``'s file."""
    from sb3_td3x.sweeps.launch import load_launcher
    from sb3_td3x.sweeps.objective import DEFAULT_CONFIG_DIR, check_composes
    from sb3_td3x.sweeps.spec import load_sweep

    check_arguments(args)
    spec = load_sweep(args.sweep_file)
    config_dir = (args.config_dir or DEFAULT_CONFIG_DIR).resolve()
    if not (config_dir / "config.yaml").is_file():
        raise SweepError(f"{config_dir} has no config.yaml; pass --config-dir pointing at the conf/ folder run.py uses")
    check_composes(spec, config_dir, args.overrides)
    if args.launcher is not None:
        load_launcher(args.launcher, Path("jobs"), "sweep")  # read again by _launch, with the study's job folder
    return spec, config_dir


def _run(args: argparse.Namespace) -> int:
    import optuna

    from sb3_td3x.sweeps.objective import TrialObjective
    from sb3_td3x.sweeps.results import write_results
    from sb3_td3x.sweeps.storage import default_storage_url, open_storage
    from sb3_td3x.sweeps.worker import SweepInterrupted, check_heartbeat_settings, open_study, run_worker

    spec, config_dir = check_command(args)
    study_name = args.study_name or spec.study_name
    n_trials = args.n_trials if args.n_trials is not None else spec.n_trials
    study_dir = (args.output_dir / study_name).resolve()
    storage_url = args.storage or spec.storage or default_storage_url(study_dir)

    if args.launcher is not None:
        return _launch(args, storage_url, study_dir, study_name, config_dir, spec.overrides)

    study_storage = open_storage(storage_url, study_name, args.heartbeat_interval, args.grace_period, args.retry_stale)
    optuna.logging.set_verbosity(optuna.logging.WARNING)  # our own log lines say what happens to each trial
    if args.report and study_name not in optuna.get_all_study_names(study_storage.storage):
        raise SweepError(f"there is no study {study_name!r} in {study_storage.display_url} to report on")
    study = open_study(spec, study_storage, study_name, spec.overrides + args.overrides)

    def finish(finished_study: optuna.Study) -> None:
        files = write_results(
            finished_study,
            study_dir,
            config_dir,
            study_storage.display_url,
            study_storage.dashboard_command(),
            study_storage.password_hint(),
        )
        print(files.summary)
        if files.best_overrides is not None:
            print(f"best overrides: {files.best_overrides}   (python run.py $(cat {files.best_overrides}))")
            print(f"as a config:    python run.py -cd {study_dir} +tuned=best")
        print(f"plots:          {', '.join(str(p) for p in files.plots) or 'none yet (too few finished trials)'}")

    if args.report:
        finish(study)
        return 0

    check_heartbeat_settings(study, study_storage)  # before anything is said about the study: a refusal comes alone
    logger.info(
        "study %s in %s: %d trials wanted, %d there", study_name, study_storage.display_url, n_trials, len(study.trials)
    )
    try:
        with stops.interrupting():  # scancel, kill: as Ctrl-C
            summary = run_worker(
                study,
                spec,
                study_storage,
                TrialObjective(spec, config_dir, args.overrides, study_dir),
                n_trials,
                args.max_consecutive_failures,
                on_finished=finish,
            )
    except SweepInterrupted as err:
        print(redact(str(err)), file=sys.stderr)
        return 130
    if not summary.ran:
        logger.info("study %s already holds its %d trials; pass a larger --n-trials to grow it", study_name, n_trials)
    return 0


def _launch(
    args: argparse.Namespace, storage_url: str, study_dir: Path, study_name: str, config_dir: Path, fixed: list[str]
) -> int:
    import optuna

    from sb3_td3x.experiment.configs.compose import compose_config
    from sb3_td3x.sweeps.launch import SweepWorkers, load_launcher
    from sb3_td3x.sweeps.storage import open_storage
    from sb3_td3x.sweeps.worker import check_heartbeat_settings

    # An unreachable storage or heartbeat settings the study refuses fail here, once, rather than in every job.
    study_storage = open_storage(storage_url, study_name, args.heartbeat_interval, args.grace_period, args.retry_stale)
    if study_name in optuna.get_all_study_names(study_storage.storage):
        study = optuna.load_study(study_name=study_name, storage=study_storage.storage)
        check_heartbeat_settings(study, study_storage, record=False)
    cluster, executor_params = load_launcher(args.launcher, study_dir / "jobs", f"sweep-{study_name}")
    if storage_url.startswith("sqlite") and cluster == "slurm":
        logger.warning(
            "SQLite on a cluster's shared file system is fragile with many workers; prefer --storage postgresql://..."
        )
    worker_argv = _worker_argv(args, _password_to_environment(storage_url), study_dir, config_dir)
    workers = SweepWorkers(cluster, executor_params, args.workers, worker_argv, main, args.wait, study_dir)
    cfg = compose_config(fixed + args.overrides, config_dir)  # a trial's config, less its searched values (check_composes ran)
    ends = workers.run(str(cfg.device), bool(cfg.mps), say=print)  # local workers on this machine's GPU: CUDA MPS
    if ends is None:
        return 0
    failed = [end for end in ends if "error" in end]
    if failed:
        raise SweepError(
            f"worker job {failed[0]['job']} ended {failed[0]['state']} without a result ({failed[0]['error']}); "
            f"see {study_dir / 'jobs'}. The study keeps every trial: run the same command again to continue it."
        )
    codes = [int(end["result"]) for end in ends]
    print(f"workers exited with {codes}")
    return max(codes)


def _password_to_environment(storage_url: str) -> str:
    """The storage URL without its password, which goes to ``$SB3_TD3X_STORAGE_PASSWORD`` of this process, so
    that the worker jobs (which inherit its environment) get it without it being written in their job files."""
    from sqlalchemy.engine import make_url

    from sb3_td3x.sweeps.storage import PASSWORD_ENV, is_journal

    if is_journal(storage_url) or "://" not in storage_url:
        return storage_url
    parsed = make_url(storage_url)  # open_storage has read it already
    if not parsed.password:
        return storage_url
    os.environ[PASSWORD_ENV] = str(parsed.password)
    return parsed._replace(password=None).render_as_string(hide_password=False)  # set() would keep it


def _worker_argv(args: argparse.Namespace, storage_url: str, study_dir: Path, config_dir: Path) -> list[str]:
    """The command line each job runs: this one, less the launcher options, with absolute paths on every node."""
    if storage_url.startswith("sqlite:///") and not storage_url.startswith("sqlite:////"):
        storage_url = f"sqlite:///{Path(storage_url.removeprefix('sqlite:///')).resolve()}"
    worker_argv = [
        str(args.sweep_file.resolve()),
        *args.overrides,
        "--storage",
        storage_url,
        "--study-name",
        study_dir.name,
        "--output-dir",
        str(study_dir.parent),
        "--config-dir",
        str(config_dir),
        "--heartbeat-interval",
        str(args.heartbeat_interval),
        "--retry-stale",
        str(args.retry_stale),
        "--max-consecutive-failures",
        str(args.max_consecutive_failures),
    ]
    if args.n_trials is not None:
        worker_argv += ["--n-trials", str(args.n_trials)]
    if args.grace_period is not None:
        worker_argv += ["--grace-period", str(args.grace_period)]
    if args.quiet:
        worker_argv.append("--quiet")
    return worker_argv


def _setup_logging(quiet: bool) -> None:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("[%(asctime)s sweep] %(message)s", datefmt="%H:%M:%S"))
    # the sweep's own lines, and how the worker jobs are followed (sb3_td3x.experiment.launch.job_watch: one line where
    # sacct does not answer)
    for name in (logger.name, "sb3_td3x.experiment.launch.job_watch"):
        logging.getLogger(name).handlers[:] = [handler]
        logging.getLogger(name).setLevel(logging.WARNING if quiet else logging.INFO)
        logging.getLogger(name).propagate = False
    redact_log_records()  # no password or key in any log line
