"""A griffe extension for the API reference: the reST markup of the package's docstrings, as Markdown.

The docstrings are written for Sphinx, as SB3's are (``:param x:`` fields, which mkdocstrings' ``sphinx`` style
reads). Two more reST constructs would show as raw text on the site, so this extension rewrites them before
mkdocstrings renders the docstrings:

* cross-reference roles, ``:meth:`sample_batch``` or ``:class:`~sb3_td3x.td3x.policies.TD3XPolicy```, become
  optional autorefs: a link where the target is documented on the site, the name as code otherwise;
* simple tables (columns under ``====  ====`` rules) become Markdown tables.

The source files are not changed. Loaded from mkdocs.yml (``extensions:`` of the python handler).
"""

from __future__ import annotations

import html
import re
from typing import Any

import griffe

ROLE = re.compile(r"(?<![\w`]):(?:py:)?(?P<role>meth|class|func|mod|attr|data|obj|exc|const):`(?P<target>[^`]+)`")
RULE = re.compile(r"^\s*=+(?: +=+)+\s*$")


def _columns(rule: str) -> list[tuple[int, int | None]]:
    spans = [(m.start(), m.end()) for m in re.finditer(r"=+", rule)]
    # The last column runs to the end of the line (text may overflow its rule).
    return [(start, None if i == len(spans) - 1 else spans[i + 1][0]) for i, (start, _) in enumerate(spans)]


def _cells(line: str, columns: list[tuple[int, int | None]]) -> list[str]:
    return [line[start:end].strip() for start, end in columns]


def simple_tables_to_markdown(text: str) -> str:
    """Rewrite reST simple tables (a rule, header rows, a rule, body rows, a rule) as Markdown tables.

    A body row whose first cell is empty continues the row above it.
    """
    lines = text.splitlines()
    out: list[str] = []
    i = 0
    while i < len(lines):
        if not RULE.match(lines[i]):
            out.append(lines[i])
            i += 1
            continue
        # The table's three rules; a blank line ends the table.
        ends = []
        for j in range(i, len(lines)):
            if not lines[j].strip():
                break
            if RULE.match(lines[j]):
                ends.append(j)
        if len(ends) < 3:
            out.append(lines[i])
            i += 1
            continue
        columns = _columns(lines[i])
        header = [_cells(line, columns) for line in lines[ends[0] + 1 : ends[1]]]
        body: list[list[str]] = []
        for line in lines[ends[1] + 1 : ends[2]]:
            cells = _cells(line, columns)
            if body and not cells[0]:
                body[-1] = [f"{a} {b}".strip() for a, b in zip(body[-1], cells)]
            else:
                body.append(cells)
        head = [" ".join(cells).strip() for cells in zip(*header)] if header else [""] * len(columns)
        if out and out[-1].strip():
            out.append("")
        out.append("| " + " | ".join(head) + " |")
        out.append("|" + "---|" * len(columns))
        out.extend("| " + " | ".join(cell.replace("|", "\\|") for cell in row) + " |" for row in body)
        if ends[2] + 1 < len(lines) and lines[ends[2] + 1].strip():
            out.append("")
        i = ends[2] + 1
    return "\n".join(out)


def _resolve(obj: griffe.Object, target: str, modules: griffe.ModulesCollection) -> str:
    """The canonical path of ``target`` as seen from ``obj``'s docstring, or ``target`` itself."""
    head, _, rest = target.partition(".")
    candidates = []
    try:
        base = obj.resolve(head)
        candidates.append(f"{base}.{rest}" if rest else base)
    except griffe.NameResolutionError:
        pass
    candidates.append(target)
    for path in candidates:
        try:
            found = modules.get_member(path)
        except (KeyError, ValueError, griffe.AliasResolutionError, griffe.CyclicAliasError):
            continue
        try:
            return found.canonical_path
        except (griffe.AliasResolutionError, griffe.CyclicAliasError):
            return path
    return candidates[0]


def roles_to_autorefs(obj: griffe.Object, text: str, modules: griffe.ModulesCollection) -> str:
    def replace(match: re.Match[str]) -> str:
        target = match["target"].strip()
        title = None
        explicit = re.fullmatch(r"(?P<title>.+?)\s*<(?P<target>[^>]+)>", target)
        if explicit:
            title, target = explicit["title"], explicit["target"]
        short = target.startswith("~")
        target = target.lstrip("~.")
        if title is None:
            title = target.rsplit(".", 1)[-1] if short else target
        identifier = _resolve(obj, target, modules)
        return f'<autoref identifier="{html.escape(identifier)}" optional><code>{html.escape(title)}</code></autoref>'

    return ROLE.sub(replace, text)


class SphinxMarkup(griffe.Extension):
    """Rewrite the reST cross-reference roles and simple tables of every docstring as Markdown."""

    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs: Any) -> None:
        modules = loader.modules_collection

        def visit(obj: griffe.Object) -> None:
            if obj.docstring is not None:
                value = simple_tables_to_markdown(obj.docstring.value)
                obj.docstring.value = roles_to_autorefs(obj, value, modules)
            for member in obj.members.values():
                if not member.is_alias:
                    visit(member)  # type: ignore[arg-type]

        visit(pkg)
