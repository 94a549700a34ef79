"""The documentation site: it builds with warnings as errors, and the built HTML holds what the pages promise.

Builds the site once into a temporary folder (``mkdocs build --strict``), then checks every page of the nav, the
rendered API reference, images and internal links; and runs the examples of docs/extending.md, which the page
includes from docs/examples/, and the other pages' Python blocks, so that the code shown keeps working.
"""

from __future__ import annotations

import importlib.util
import inspect
import os
import re
import subprocess
import sys
import textwrap
from html.parser import HTMLParser
from pathlib import Path
from types import ModuleType
from urllib.parse import unquote, urlsplit

import pytest
import torch as th
import yaml
from stable_baselines3.common.type_aliases import ReplayBufferSamples

from sb3_td3x import TD3X
from sb3_td3x.td3x.hooks import HOOK_NAMES

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
EXAMPLES = sorted((DOCS / "examples").glob("*.py"))

# The hooks of TD3X (steps 4 to 15, sb3_td3x.td3x.hooks): each must be rendered on the API page with its docstring.
HOOKS = list(HOOK_NAMES)


class _Page(HTMLParser):
    """Collects ids, links, image and script sources, the <title>, the <h1> and the article's text of a page."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.ids: set[str] = set()
        self.links: list[str] = []
        self.sources: list[tuple[str, str]] = []  # (tag, src)
        self.title = ""
        self.h1: list[str] = []
        self.article: list[str] = []
        self._in: dict[str, int] = {"title": 0, "h1": 0, "article": 0}

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        attributes = dict(attrs)
        for key in ("id", "name"):
            if attributes.get(key):
                self.ids.add(attributes[key])  # type: ignore[arg-type]
        if tag == "a" and attributes.get("href"):
            self.links.append(attributes["href"])  # type: ignore[arg-type]
        if tag in ("img", "script", "source") and attributes.get("src"):
            self.sources.append((tag, attributes["src"]))  # type: ignore[arg-type]
        if tag in self._in:
            self._in[tag] += 1

    def handle_endtag(self, tag: str) -> None:
        if self._in.get(tag):
            self._in[tag] -= 1

    def handle_data(self, data: str) -> None:
        if self._in["title"]:
            self.title += data
        if self._in["h1"]:
            self.h1.append(data)
        if self._in["article"]:
            self.article.append(data)

    @property
    def text(self) -> str:
        return " ".join("".join(self.article).split())


def parse(path: Path) -> _Page:
    page = _Page()
    page.feed(path.read_text(encoding="utf-8"))
    return page


def nav_pages() -> list[tuple[str, str]]:
    """(title, source file) of every page in mkdocs.yml's nav, nested sections included."""

    class Loader(yaml.SafeLoader):
        """Reads MkDocs' Python tags (``!!python/name:...``, ``!ENV``) as plain values."""

    Loader.add_multi_constructor("", lambda loader, suffix, node: None)
    config = yaml.load((ROOT / "mkdocs.yml").read_text(encoding="utf-8"), Loader=Loader)

    def walk(items: list) -> list[tuple[str, str]]:
        pages = []
        for item in items:
            for title, value in item.items():
                pages.extend(walk(value) if isinstance(value, list) else [(title, value)])
        return pages

    return walk(config["nav"])


def html_path(site: Path, source: str) -> Path:
    # use_directory_urls is false in mkdocs.yml: docs/x.md -> site/x.html
    return site / Path(source).with_suffix(".html")


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    pytest.importorskip("mkdocs", reason="the docs extra: pip install -e '.[docs]'")
    out = tmp_path_factory.mktemp("site")
    result = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},  # no banner about MkDocs 2 in the output
    )
    assert result.returncode == 0, f"mkdocs build --strict failed:\n{result.stdout}\n{result.stderr}"
    return out


def test_nav_lists_every_page_and_every_page_is_in_nav():
    listed = {source for _, source in nav_pages()}
    on_disk = {str(p.relative_to(DOCS)) for p in DOCS.rglob("*.md")}
    assert listed == on_disk, f"in nav but missing: {listed - on_disk}; on disk but not in nav: {on_disk - listed}"


@pytest.mark.parametrize(("title", "source"), nav_pages())
def test_page_is_built_with_its_title_heading_and_content(site: Path, title: str, source: str):
    path = html_path(site, source)
    assert path.is_file(), f"{source} was not built to {path.relative_to(site)}"
    page = parse(path)

    # The <title>: "<nav title> - <site name>", the home page only the site name.
    expected = "sb3-td3x" if source == "index.md" else f"{title} - sb3-td3x"
    assert page.title.strip() == expected

    # The <h1> is the Markdown's first heading.
    first_heading = next(
        line[2:].strip() for line in (DOCS / source).read_text(encoding="utf-8").splitlines() if line.startswith("# ")
    )
    rendered_h1 = " ".join("".join(page.h1).split())
    expected_h1 = " ".join(re.sub(r"`([^`]*)`", r"\1", first_heading).split())
    assert rendered_h1.startswith(expected_h1), f"{source}: <h1> is {rendered_h1!r}, expected {expected_h1!r}"

    # Non-trivial content: more than a heading and a placeholder.
    assert len(page.text) > 1500, f"{source}: only {len(page.text)} characters of text"
    assert "TODO" not in page.text


def test_api_reference_renders_td3x_and_its_hooks(site: Path):
    page = parse(site / "api.html")
    text = page.text
    for name in ("sb3_td3x.TD3X", "sb3_td3x.DDPG", "sb3_td3x.common.buffers.TensorReplayBuffer"):
        assert name in page.ids, f"no anchor for {name} on the API page"
    # TD3X's own docstring and its parameters table (sphinx-style :param: fields).
    assert "Twin Delayed DDPG (TD3), with every step of the algorithm an overridable method" in text
    for param in ("target_policy_noise", "critic_learning_rate", "target_policy_smoothing", "clipped_double_q"):
        assert param in text
    # Every hook: an anchor and its docstring's first line.
    for hook in HOOKS:
        assert f"sb3_td3x.TD3X.{hook}" in page.ids, f"hook {hook} is not rendered on the API page"
        summary = inspect.getdoc(getattr(TD3X, hook)).splitlines()[0]
        summary = " ".join(summary.replace("``", "").split())
        assert summary in text, f"the docstring of {hook} is not rendered: {summary!r}"


def test_api_reference_td3x_step_table_links_every_hook(site: Path):
    """The step table of TD3X's docstring (a reST table, rendered by docs/_griffe/sphinx_markup.py) links each hook."""
    source = (site / "api.html").read_text(encoding="utf-8")
    start = source.index("reads as the algorithm")
    table = source[start : source.index("</table>", start)]
    assert "====" not in table, "the reST table of TD3X's docstring was not converted"
    missing = [hook for hook in HOOKS if f'href="#sb3_td3x.TD3X.{hook}"' not in table]
    assert not missing, f"the step table does not link {missing}"


def test_the_extending_page_links_every_hook():
    """docs/extending.md says what to override for what: every hook of the one list (sb3_td3x.td3x.hooks) is linked
    there, so that a hook added to the list is added to the page too."""
    text = (DOCS / "extending.md").read_text(encoding="utf-8")
    missing = [hook for hook in HOOKS if f"[sb3_td3x.TD3X.{hook}]" not in text]
    assert not missing, f"docs/extending.md does not link {missing}"


def _local_target(site: Path, page: Path, url: str) -> tuple[Path, str] | None:
    """The file and fragment a relative URL of ``page`` points to; None for external or special URLs."""
    parts = urlsplit(url)
    if parts.scheme or parts.netloc or url.startswith(("mailto:", "javascript:")):
        return None
    target = page if not parts.path else (page.parent / unquote(parts.path)).resolve()
    if target.is_dir():
        target = target / "index.html"
    return target, unquote(parts.fragment)


@pytest.mark.parametrize(("title", "source"), nav_pages())
def test_images_scripts_and_internal_links_resolve(site: Path, title: str, source: str):
    path = html_path(site, source)
    page = parse(path)
    problems = []
    for tag, src in page.sources:
        target = _local_target(site, path, src)
        if target is not None and not target[0].is_file():
            problems.append(f"<{tag} src={src!r}>: no such file in the built site")
    ids_of: dict[Path, set[str]] = {path.resolve(): page.ids}
    for href in page.links:
        target = _local_target(site, path, href)
        if target is None:
            continue
        file, fragment = target
        if not file.is_file():
            problems.append(f"link {href!r}: no such file in the built site")
            continue
        if fragment and file.suffix == ".html":
            if file not in ids_of:
                ids_of[file] = parse(file).ids
            if fragment not in ids_of[file]:
                problems.append(f"link {href!r}: no element with id {fragment!r}")
    assert not problems, f"{source}:\n" + "\n".join(problems)


def test_images_referenced_in_markdown_exist():
    """Markdown image references point at files in docs/ (the built-site check covers the HTML they become)."""
    missing = []
    for md in DOCS.rglob("*.md"):
        for src in re.findall(r"!\[[^\]]*\]\(([^)\s]+)", md.read_text(encoding="utf-8")):
            if not urlsplit(src).scheme and not (md.parent / src).is_file():
                missing.append(f"{md.relative_to(DOCS)}: {src}")
    assert not missing


# The project's own work items ("issue 36", "#35") mean nothing to a reader. The only numbered references allowed are
# other projects' issues, cited as such: Hydra's, in docs/sweeps.md.
INTERNAL_ISSUE = re.compile(r"\b[Ii]ssues? \d+|(?<![\w/&])#\d+\b")
OTHER_PROJECTS_ISSUES = {"#1710", "#1954", "#2237"}


@pytest.mark.parametrize("path", [*sorted(DOCS.glob("*.md")), ROOT / "README.md"], ids=lambda p: p.name)
def test_no_internal_issue_numbers(path: Path):
    found = [
        f"line {number}: {match.group()!r}"
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        for match in INTERNAL_ISSUE.finditer(re.sub(r"https?://\S+", "", line))
        if match.group() not in OTHER_PROJECTS_ISSUES
    ]
    assert not found, f"{path.name} names the project's issues; say what was measured or built instead: {found}"


def test_performance_page_is_a_summary_with_a_table_per_kind_of_machine():
    """docs/performance.md is read in a minute: a table for each kind of machine measured; the full entries live in
    docs/performance_log.md."""
    text = (DOCS / "performance.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 250
    sections = re.split(r"^## ", text, flags=re.MULTILINE)
    for machine in ("Intel Xeon", "AMD EPYC", "NVIDIA GPU"):
        section = next((s for s in sections if s.startswith(machine)), None)
        assert section is not None, f"no section for {machine}"
        assert re.search(r"^\| date \|", section, flags=re.MULTILINE), f"{machine}: no table with dated rows"
    assert "(performance_log.md)" in text


# The examples of docs/extending.md ----------------------------------------------------------------------------------


def load_example(path: Path) -> tuple[ModuleType, type[TD3X]]:
    spec = importlib.util.spec_from_file_location(f"docs_example_{path.stem}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # as an imported file is: torch.compile looks its globals up by module name
    spec.loader.exec_module(module)
    classes = [
        obj
        for obj in vars(module).values()
        if inspect.isclass(obj) and issubclass(obj, TD3X) and obj is not TD3X and obj.__module__ == module.__name__
    ]
    assert len(classes) == 1, f"{path.name} should define one TD3X subclass, found {classes}"
    return module, classes[0]


def overridden_hooks(cls: type[TD3X]) -> list[str]:
    return [name for name in HOOKS if name in vars(cls)]


def test_there_are_examples():
    assert {p.name for p in EXAMPLES} >= {"huber_critic_loss.py", "soft_pessimism.py", "gradient_clipping.py"}


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.stem)
def test_example_is_shown_on_the_extending_page(site: Path, path: Path):
    text = parse(site / "extending.html").text
    _, cls = load_example(path)
    assert f"class {cls.__name__}(TD3X):" in text, f"{path.name} is not included in extending.md"


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.stem)
def test_example_trains_and_calls_its_override(path: Path, monkeypatch: pytest.MonkeyPatch):
    _, cls = load_example(path)
    hooks = overridden_hooks(cls)
    assert hooks, f"{cls.__name__} overrides no hook of TD3X"
    calls = dict.fromkeys(hooks, 0)
    for name in hooks:
        original = vars(cls)[name]

        def spy(self, *args, _name=name, _original=original, **kwargs):
            calls[_name] += 1
            return _original(self, *args, **kwargs)

        monkeypatch.setattr(cls, name, spy)

    model = cls("MlpPolicy", "Pendulum-v1", policy_kwargs={"net_arch": [32, 32]}, learning_starts=100, seed=0)
    model.learn(total_timesteps=200)
    assert model._n_updates == 100
    assert all(n > 0 for n in calls.values()), f"overrides not called during training: {calls}"
    for p in model.policy.parameters():
        assert th.isfinite(p).all()


def page_python_blocks() -> list[tuple[str, int, str]]:
    """The ``python`` code blocks of docs/'s pages as (page, line, code), less those that include a file of
    docs/examples/ (run above)."""
    blocks = []
    for page in sorted(DOCS.glob("*.md")):
        text = page.read_text(encoding="utf-8")
        for match in re.finditer(r"^```python\n(.*?)^```", text, flags=re.DOTALL | re.MULTILINE):
            if "--8<--" not in match.group(1):
                blocks.append((page.name, text.count("\n", 0, match.start()) + 1, match.group(1)))
    return blocks


@pytest.mark.parametrize("page, line, code", [pytest.param(*b, id=f"{b[0]}:{b[1]}") for b in page_python_blocks()])
def test_a_pages_python_block_runs(page: str, line: int, code: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """Each block as written, in a namespace of its own, from an empty folder; every ``learn()`` (a TD3X's, a seed
    batch's) cut to 200 steps, so that a page's ``learn(200_000)`` runs what its code says, for a moment."""
    from sb3_td3x import SeedBatch

    for cls in (TD3X, SeedBatch):
        learn = cls.learn
        monkeypatch.setattr(cls, "learn", lambda self, total_timesteps, *a, _learn=learn, **k: _learn(self, 200, *a, **k))
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": f"docs_{page[:-3]}_{line}"}
    exec(compile(code, f"docs/{page}:{line}", "exec"), namespace)  # noqa: S102  (the page's own code)


def _example_class(stem: str) -> type[TD3X]:
    return load_example(DOCS / "examples" / f"{stem}.py")[1]


def _small(cls: type[TD3X], **kwargs) -> TD3X:
    return cls("MlpPolicy", "Pendulum-v1", policy_kwargs={"net_arch": [8]}, learning_starts=0, seed=0, **kwargs)


def test_huber_example_computes_the_huber_loss():
    model = _small(_example_class("huber_critic_loss"), huber_delta=1.0)
    current_q = th.zeros(2, 4, 1)  # (n_critics, batch_size, 1)
    target_q = th.full((4, 1), 10.0)
    loss, info = model.critic_loss(current_q, target_q)
    # |TD error| = 10 > delta = 1: delta * (10 - delta / 2) = 9.5 per critic, summed over 2 critics (MSE: 200)
    assert loss.item() == pytest.approx(19.0)
    assert info["critic_loss"].item() == pytest.approx(19.0)


def test_soft_pessimism_example_mixes_min_and_mean():
    cls = _example_class("soft_pessimism")
    next_q = th.tensor([1.0, 3.0]).reshape(2, 1, 1).expand(2, 5, 1)  # (n_critics, batch_size, 1)
    assert th.allclose(_small(cls, pessimism=0.75).clipped_double_q_value(next_q), th.full((5, 1), 1.25))
    assert th.allclose(_small(cls, pessimism=1.0).clipped_double_q_value(next_q), th.full((5, 1), 1.0))  # TD3
    with pytest.raises(ValueError):
        _small(cls, pessimism=1.5)


def test_gradient_clipping_example_clips_the_critic_gradient():
    model = _small(_example_class("gradient_clipping"), max_grad_norm=1e-3)
    batch = ReplayBufferSamples(th.randn(16, 3), th.rand(16, 1) * 2 - 1, th.randn(16, 3), th.zeros(16, 1), th.randn(16, 1))
    loss = 1e6 * model.current_q_values(batch).pow(2).mean()
    model.optimize_critic(loss)
    norm = th.linalg.vector_norm(th.stack([p.grad.norm() for p in model.critic.parameters() if p.grad is not None]))
    assert norm.item() <= 1e-3 * (1 + 1e-4)


def test_gradient_clipping_example_compiles_in_one_graph(monkeypatch: pytest.MonkeyPatch):
    """The page says the clipped step, written with gradients() and apply_gradients(), compiles with the rest of the
    update: with compile_update=True its update is one graph (Dynamo's graph run by AOTAutograd's eager kernels,
    ``aot_eager``, to stay fast), not the eager update that stepped aside."""
    from sb3_td3x.td3x.update_paths.compiled import CompiledUpdate

    monkeypatch.setattr(CompiledUpdate, "backend", "aot_eager")
    cls = _example_class("gradient_clipping")
    model = cls("MlpPolicy", "Pendulum-v1", policy_kwargs={"net_arch": [16]}, learning_starts=50, batch_size=32, seed=0,
                max_grad_norm=0.05, compile_update=True)  # fmt: skip
    before = [p.detach().clone() for p in model.critic.parameters()]
    model.learn(80)
    assert model.update_path == "compiled", model.update_reason
    assert all(th.isfinite(p).all() for p in model.policy.parameters())
    assert any(not th.equal(a, b) for a, b in zip(before, model.critic.parameters()))


# The griffe extension that renders reST markup of docstrings (docs/_griffe/sphinx_markup.py) ------------------------


def test_simple_table_becomes_a_markdown_table():
    spec = importlib.util.spec_from_file_location("sphinx_markup", DOCS / "_griffe" / "sphinx_markup.py")
    assert spec is not None and spec.loader is not None
    markup = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(markup)
    text = textwrap.dedent(
        """\
        Intro:

        ====  ======  =====
        step  what    hook
        ====  ======  =====
        4     sample  :meth:`a`
        13    actor   :meth:`b`,
                      :meth:`c`
        ====  ======  =====

        After."""
    )
    assert markup.simple_tables_to_markdown(text).splitlines() == [
        "Intro:",
        "",
        "| step | what | hook |",
        "|---|---|---|",
        "| 4 | sample | :meth:`a` |",
        "| 13 | actor | :meth:`b`, :meth:`c` |",
        "",
        "After.",
    ]
