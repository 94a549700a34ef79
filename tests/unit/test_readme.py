"""The README: short, its links lead somewhere, and its Python examples run and do what it says of them."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch as th

from sb3_td3x import TD3X

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "README.md").read_text(encoding="utf-8")


def python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", README, flags=re.DOTALL)


def test_the_readme_is_short():
    assert len(README.split()) < 600  # as `wc -w` counts


def test_the_readme_links_lead_to_files_and_headings():
    for target in re.findall(r"\]\(([^)]+)\)", README):
        if target.startswith("http"):
            continue
        path, _, anchor = target.partition("#")
        assert (ROOT / path).exists(), target
        if anchor:
            headings = re.findall(r"^#+ (.+)$", (ROOT / path).read_text(encoding="utf-8"), flags=re.MULTILINE)
            slugs = {re.sub(r"[^\w\- ]", "", heading.lower()).strip().replace(" ", "-") for heading in headings}
            assert anchor in slugs, target


def test_the_python_examples_run(tmp_path, monkeypatch):
    """The first example as written (its learn() cut to 300 steps); the override of the second trains with its own
    loss, run as written (eagerly: a short run)."""
    first, override = python_blocks()
    monkeypatch.chdir(tmp_path)
    learn = TD3X.learn
    monkeypatch.setattr(TD3X, "learn", lambda self, total_timesteps, **kwargs: learn(self, min(total_timesteps, 300), **kwargs))
    names: dict = {}
    exec(compile(first, "README.md", "exec"), names)
    assert names["model"].num_timesteps == 300 and (tmp_path / "td3x_pendulum.zip").is_file()
    assert names["ablation"].target_policy_smoothing is False
    exec(compile(override, "README.md", "exec"), names)
    model = names["HuberTD3"]("MlpPolicy", "Pendulum-v1", learning_starts=100, batch_size=32, buffer_size=1000, seed=0)
    model.learn(200)
    assert model.update_path == "eager" and model._n_updates == 100
    current_q, target_q = th.zeros(2, 4, 1), th.full((4, 1), 3.0)
    loss, _ = model.critic_loss(current_q, target_q)
    assert float(loss) == 2 * (3.0 - 0.5)  # the Huber loss of each critic, summed


@pytest.mark.parametrize("command", ["python run.py", "bash scripts/test.sh"])
def test_the_set_up_commands_are_there(command):
    assert command in README and (ROOT / command.split()[-1]).is_file()
