"""The search-space file: what a sweep tunes, how it samples and prunes, and how many trials it runs.

A sweep file (``sweeps/*.yaml``) reads::

    study_name: td3x-pendulum
    metric: eval/mean_return        # the final evaluation; or eval/best_mean_return
    direction: maximize
    n_trials: 40                     # trials the study holds in total, shared by every worker
    seed: 0                          # trial k trains with seed + k (seeds seed + k*K ... with seeds_per_trial K)
    seeds_per_trial: 1               # K seeds trained together in each trial's process; default 1
    seeds_aggregate: mean            # with K > 1: the trial's value over its seeds, mean or iqm
    storage: null                    # null: an SQLite file in the study folder
    overrides: [env=pendulum, total_timesteps=20000]   # fixed Hydra overrides, as run.py takes them
    sampler: {_target_: optuna.samplers.TPESampler, seed: 0, multivariate: true}
    pruner: {_target_: optuna.pruners.MedianPruner, n_startup_trials: 5, n_warmup_steps: 5000}
    search_space:                    # config paths of conf/, exactly as run.py composes them
      algo.learning_rate: {low: 1.0e-4, high: 3.0e-3, log: true}
      algo.batch_size: {choices: [64, 128, 256]}
      algo.policy_delay: {low: 1, high: 4}
      algo.net_arch: {choices: [[64, 64], [256, 256]]}

A parameter is a range (``low``/``high``, with ``log`` or ``step``; integers when both ends are integers, or say
``type: float``) or a list of ``choices``. A choice may be a list or a mapping (``net_arch``); Optuna stores such a
choice as its Hydra override text (``"[64,64]"``), so that the dashboard and the best-parameters file show it.

``seeds_per_trial: K`` (an integer, at least 1; default 1) trains K seeds in every trial, together in the trial's
process (the runner's ``seeds=[...]``). Trial ``n`` trains seeds ``seed + n*K + j`` for ``j < K``, so that no two
trials share a seed and a trial's seeds follow from its number alone; with K = 1 that is ``seed + n``, as without
the field. At every evaluation the pruner sees the aggregate over the K seeds; the trial's value is the aggregate
of their final evaluations (for ``eval/best_mean_return``: the best aggregated evaluation). ``seeds_aggregate``
picks the aggregate: ``mean`` (default) or ``iqm``, the interquartile mean of
:func:`sb3_td3x.experiment.analysis.aggregate.iqm` (the mean of the middle half; for K < 4 it is the mean).
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import optuna
import yaml
from omegaconf import MISSING, DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException
from optuna.distributions import BaseDistribution, CategoricalDistribution, FloatDistribution, IntDistribution

from sb3_td3x.experiment.analysis.statistics import STATISTICS
from sb3_td3x.sweeps.errors import SweepSpecError

#: Metrics a trial can be scored by, with the direction that improves them.
METRICS = {
    "eval/mean_return": "maximize",  # the mean return of the final evaluation (what the runner returns)
    "eval/best_mean_return": "maximize",  # the best mean return over the periodic evaluations
}

_RANGE_KEYS = {"low", "high", "log", "step", "type"}
_CHOICE_KEYS = {"choices", "type"}
_TYPES = {"float", "int", "categorical"}
_BARE_STRING = re.compile(r"^[A-Za-z_][\w\-./]*$")
#: How a trial of several seeds turns their evaluations into one value.
SEEDS_AGGREGATES = tuple(STATISTICS)


@dataclass
class SweepFileSchema:
    """The fields of a sweep file and their types; OmegaConf checks a loaded file against it."""

    study_name: str = MISSING
    metric: str = MISSING
    direction: str = MISSING
    n_trials: int = MISSING
    seed: int = 0
    seeds_per_trial: int = 1
    seeds_aggregate: str = "mean"
    storage: str | None = None
    overrides: list[str] = field(default_factory=list)
    sampler: dict[str, Any] = MISSING
    pruner: dict[str, Any] = MISSING
    search_space: dict[str, Any] = MISSING


def override_value(value: Any) -> str:
    """Write ``value`` in Hydra's override grammar: ``0.001``, ``true``, ``null``, ``[64,64]``, ``'two words'``."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        if _BARE_STRING.match(value) and value.lower() not in {"null", "true", "false", "nan", "inf"}:
            return value
        return "'" + value.replace("\\", "\\\\").replace("'", "\\'") + "'"
    if isinstance(value, list | tuple):
        return "[" + ",".join(override_value(item) for item in value) + "]"
    if isinstance(value, dict):
        return "{" + ",".join(f"{key}:{override_value(item)}" for key, item in value.items()) + "}"
    raise TypeError(f"cannot write {value!r} of type {type(value).__name__} as a Hydra override value")


@dataclass(frozen=True)
class ParamSpec:
    """One searched config path and the Optuna distribution it is drawn from."""

    path: str
    distribution: BaseDistribution
    #: choices stored as their Hydra override text because they are lists or mappings (``"[64,64]"``)
    structured_choices: frozenset[str] = frozenset()

    def suggest(self, trial: optuna.Trial) -> Any:
        """Draw this parameter for ``trial``; the Optuna parameter name is the config path."""
        dist = self.distribution
        if isinstance(dist, FloatDistribution):
            return trial.suggest_float(self.path, dist.low, dist.high, log=dist.log, step=dist.step)
        if isinstance(dist, IntDistribution):
            return trial.suggest_int(self.path, dist.low, dist.high, log=dist.log, step=dist.step)
        assert isinstance(dist, CategoricalDistribution)
        return trial.suggest_categorical(self.path, dist.choices)

    def override(self, value: Any) -> str:
        """The Hydra override that sets this path to ``value`` (a list choice is already its override text)."""
        if value in self.structured_choices:
            return f"{self.path}={value}"
        return f"{self.path}={override_value(value)}"

    def example_value(self) -> Any:
        """A value inside the range, used to check that the path composes before any trial runs."""
        dist = self.distribution
        if isinstance(dist, CategoricalDistribution):
            return dist.choices[0]
        return dist.low


@dataclass(frozen=True)
class SweepSpec:
    """A checked sweep file."""

    source: Path
    study_name: str
    metric: str
    direction: str
    n_trials: int
    seed: int
    storage: str | None
    overrides: list[str]
    sampler: dict[str, Any]
    pruner: dict[str, Any]
    params: list[ParamSpec]
    seeds_per_trial: int = 1  #: seeds trained together in each trial
    seeds_aggregate: str = "mean"  #: how their evaluations become the trial's: ``mean`` or ``iqm``

    def trial_seeds(self, number: int) -> list[int]:
        """The seeds of trial ``number``: ``seed + number*K + j`` for ``j < K`` (``[seed + number]`` for K = 1)."""
        first = self.seed + number * self.seeds_per_trial
        return list(range(first, first + self.seeds_per_trial))

    def make_sampler(self, seed_offset: int = 0) -> optuna.samplers.BaseSampler:
        """Build the sampler; a seeded sampler gets ``seed + seed_offset`` so that workers do not draw alike."""
        config = dict(self.sampler)
        if config.get("seed") is not None:
            config["seed"] = int(config["seed"]) + seed_offset
        return _instantiate(config, optuna.samplers.BaseSampler, "sampler", self.source)

    def make_pruner(self) -> optuna.pruners.BasePruner:
        return _instantiate(dict(self.pruner), optuna.pruners.BasePruner, "pruner", self.source)

    @property
    def searched_paths(self) -> list[str]:
        return [param.path for param in self.params]


def _instantiate(config: dict[str, Any], base: type, what: str, source: Path) -> Any:
    from hydra.errors import HydraException
    from hydra.utils import instantiate

    if "_target_" not in config:
        raise SweepSpecError(
            f"{source}: '{what}' needs a '_target_', e.g. {what}: {{_target_: "
            f"{'optuna.samplers.TPESampler' if what == 'sampler' else 'optuna.pruners.MedianPruner'}, ...}}"
        )
    try:
        obj = instantiate(config)
    except HydraException as err:  # InstantiationException: an unknown _target_, or arguments it does not take
        raise SweepSpecError(f"{source}: cannot build the {what} {config['_target_']!r}: {_first_line(err)}") from None
    if not isinstance(obj, base):
        raise SweepSpecError(f"{source}: '{what}._target_' {config['_target_']!r} is not an Optuna {base.__name__}")
    return obj


def _first_line(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[-1] if text else type(err).__name__


def parse_param(path: str, entry: Any, source: Path) -> ParamSpec:
    """Check one ``search_space`` entry and turn it into a :class:`ParamSpec`."""
    where = f"{source}: search_space.{path}"
    example = "{low: 1.0e-4, high: 1.0e-3, log: true} or {choices: [64, 128, 256]}"
    if not re.fullmatch(r"[A-Za-z_][\w]*(\.[A-Za-z_][\w]*)*", path):
        raise SweepSpecError(f"{where}: a search-space key must be a config path such as algo.learning_rate")
    if not isinstance(entry, dict):
        raise SweepSpecError(f"{where} must be a mapping such as {example}, not {entry!r}")
    kind = entry.get("type")
    if kind is not None and kind not in _TYPES:
        raise SweepSpecError(f"{where}: type must be one of {sorted(_TYPES)}, not {kind!r}")

    if "choices" in entry:
        unknown = set(entry) - _CHOICE_KEYS
        if unknown:
            raise SweepSpecError(f"{where}: {sorted(unknown)} cannot go with 'choices' (allowed: choices, type)")
        choices = entry["choices"]
        if not isinstance(choices, list) or not choices:
            raise SweepSpecError(f"{where}: choices must be a non-empty list, e.g. {{choices: [64, 128, 256]}}")
        stored = tuple(override_value(c) if isinstance(c, list | dict) else c for c in choices)
        if len(set(map(repr, stored))) != len(stored):
            raise SweepSpecError(f"{where}: choices repeat a value: {choices}")
        structured = frozenset(s for s, c in zip(stored, choices) if isinstance(c, list | dict))
        return ParamSpec(path, CategoricalDistribution(stored), structured)

    unknown = set(entry) - _RANGE_KEYS
    if unknown or "low" not in entry or "high" not in entry:
        raise SweepSpecError(
            f"{where} must give a range {{low, high}} (optional: log, step, type) or a list of choices, "
            f"e.g. {example}; got keys {sorted(entry)}"
        )
    low, high, log, step = entry["low"], entry["high"], entry.get("log", False), entry.get("step")
    for name, value in (("low", low), ("high", high), ("step", step)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, int | float)):
            raise SweepSpecError(f"{where}: {name} must be a number, not {value!r}")
    if not isinstance(log, bool):
        raise SweepSpecError(f"{where}: log must be true or false, not {log!r}")
    if not low < high:
        raise SweepSpecError(f"{where}: low ({low}) must be smaller than high ({high})")
    if log and low <= 0:
        raise SweepSpecError(f"{where}: a log range needs low > 0, got low={low}")
    if log and step is not None:
        raise SweepSpecError(f"{where}: give either log or step, not both")
    if kind == "categorical":
        raise SweepSpecError(f"{where}: type categorical needs 'choices', not a range")
    is_int = kind == "int" or (kind is None and all(isinstance(v, int) for v in (low, high, step) if v is not None))
    try:
        if is_int:
            if any(isinstance(v, float) and not v.is_integer() for v in (low, high, step) if v is not None):
                raise SweepSpecError(f"{where}: type int needs whole numbers for low, high and step")
            dist: BaseDistribution = IntDistribution(int(low), int(high), log=log, step=int(step or 1))
        else:
            dist = FloatDistribution(float(low), float(high), log=log, step=None if step is None else float(step))
    except ValueError as err:  # Optuna's own range checks, e.g. a step that does not divide the range
        raise SweepSpecError(f"{where}: {err}") from None
    return ParamSpec(path, dist)


def check_readable_file(source: Path, what: str, hint: str) -> None:
    """Raise a :class:`SweepSpecError` that says why ``source`` cannot be read: missing, a folder, or no permission."""
    if source.is_dir():
        raise SweepSpecError(f"{what} {source} is a folder; pass a YAML file ({hint})")
    if not source.is_file():
        raise SweepSpecError(f"{what} {source} does not exist ({hint})")
    if not os.access(source, os.R_OK):
        raise SweepSpecError(
            f"{what} {source} cannot be read: permission denied for this user; make it readable (chmod u+r {source})"
        )


def load_sweep(path: str | Path) -> SweepSpec:
    """Read and check a sweep file; every problem is a :class:`SweepSpecError` that names the file and field."""
    source = Path(path)
    check_readable_file(source, "sweep file", "the ready ones are in sweeps/*.yaml")
    try:
        loaded = OmegaConf.load(source)
    except (yaml.YAMLError, UnicodeDecodeError) as err:  # report the position, not the parser's stack
        raise SweepSpecError(f"{source} is not valid YAML: {err}") from None
    except OSError as err:  # unreadable after all (a file system error): say so, not a traceback
        raise SweepSpecError(f"sweep file {source} cannot be read: {err.strerror}") from None
    if not isinstance(loaded, DictConfig):
        raise SweepSpecError(f"{source} must be a mapping of fields (study_name, metric, ...), not a list")
    # Overrides stay verbatim: an interpolation in them (algo.gradient_steps=${algo.train_freq}) belongs to the
    # training config, not to this file.
    overrides = OmegaConf.to_container(loaded, resolve=False).get("overrides", [])
    if not isinstance(overrides, list) or not all(isinstance(o, str) for o in overrides):
        raise SweepSpecError(
            f"{source}: overrides must be a list of Hydra overrides such as [env=hopper, total_timesteps=300000]"
        )
    loaded.overrides = []
    _check_seeds_fields(OmegaConf.to_container(loaded, resolve=False), source)
    try:
        config = OmegaConf.merge(OmegaConf.structured(SweepFileSchema), loaded)
        missing = sorted(OmegaConf.missing_keys(config))
        if missing:
            raise SweepSpecError(f"{source} lacks the field(s) {', '.join(missing)}; see sweeps/pendulum.yaml")
        data = OmegaConf.to_container(config, resolve=True)
    except OmegaConfBaseException as err:
        raise SweepSpecError(f"{source}: {_omegaconf_message(err)}") from None
    assert isinstance(data, dict)

    metric, direction = data["metric"], data["direction"]
    if metric not in METRICS:
        raise SweepSpecError(f"{source}: metric must be one of {sorted(METRICS)}, not {metric!r}")
    if direction != METRICS[metric]:
        raise SweepSpecError(f"{source}: metric {metric} is a return, so direction must be {METRICS[metric]!r}")
    if data["n_trials"] < 1:
        raise SweepSpecError(f"{source}: n_trials must be at least 1, got {data['n_trials']}")
    if not re.fullmatch(r"[\w.\-]+", data["study_name"]):
        raise SweepSpecError(f"{source}: study_name {data['study_name']!r} may hold only letters, digits, '.', '_', '-'")
    if not data["search_space"]:
        raise SweepSpecError(f"{source}: search_space is empty; give at least one config path to tune")

    params = [parse_param(str(key), entry, source) for key, entry in data["search_space"].items()]
    spec = SweepSpec(
        source=source,
        study_name=data["study_name"],
        metric=metric,
        direction=direction,
        n_trials=data["n_trials"],
        seed=data["seed"],
        storage=data["storage"],
        overrides=list(overrides),
        sampler=data["sampler"],
        pruner=data["pruner"],
        params=params,
        seeds_per_trial=data["seeds_per_trial"],
        seeds_aggregate=data["seeds_aggregate"],
    )
    spec.make_sampler()  # build both once so that a bad _target_ or argument is reported now, not in a trial
    spec.make_pruner()
    return spec


def _check_seeds_fields(raw: dict[str, Any], source: Path) -> None:
    """``seeds_per_trial`` and ``seeds_aggregate`` as written (before OmegaConf converts ``"2"`` or ``3``)."""
    k = raw.get("seeds_per_trial", 1)
    if isinstance(k, bool) or not isinstance(k, int) or k < 1:
        raise SweepSpecError(
            f"{source}: seeds_per_trial must be an integer of at least 1 (the seeds each trial trains together; "
            f"1 trains one seed per trial), not {k!r}"
        )
    aggregate = raw.get("seeds_aggregate", "mean")
    if aggregate not in SEEDS_AGGREGATES:
        raise SweepSpecError(
            f"{source}: seeds_aggregate must be one of {', '.join(SEEDS_AGGREGATES)} (how a trial's seeds make its "
            f"value), not {aggregate!r}"
        )


def _omegaconf_message(err: OmegaConfBaseException) -> str:
    """OmegaConf's message without its 'full_key / object_type' trailer lines, plus which field it was."""
    lines = [line for line in str(err).splitlines() if line.strip()]
    key = getattr(err, "full_key", None)
    message = lines[0] if lines else type(err).__name__
    if "not in 'SweepFileSchema'" in message:
        allowed = ", ".join(SweepFileSchema.__dataclass_fields__)
        return f"{message} (a sweep file has the fields {allowed})"
    return f"field {key!r}: {message}" if key else message
