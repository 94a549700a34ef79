"""Secrets never reach a record: one function, :func:`redact`, masks them in whatever is written or logged.

What counts as a secret:

* the password of a URL (``postgresql://user:PASSWORD@host/db``, any SQLAlchemy URL): masked by SQLAlchemy's own
  ``URL.render_as_string(hide_password=True)``; a URL SQLAlchemy cannot parse (a raw ``@`` in the password) is
  masked up to its last ``@``;
* the value under a secret-like name (:func:`is_secret_name`: ``WANDB_API_KEY``, any ``*_KEY``, ``*_TOKEN``,
  ``*_PASSWORD``, ``*_SECRET``, ``api_key``, ``password``), wherever it appears: ``name=value`` (command-line
  overrides such as ``+env.kwargs.api_key=...``, ``hydra.job.env_set.WANDB_API_KEY=...``, environment assignments,
  URL query strings), ``--name value`` and ``--name=value`` options, ``name: value`` lines (YAML) and
  ``"name": "value"`` (JSON, Python reprs), and the keys of mappings (configs, environments);
* the literal value of a secret-like environment variable of this process (8 characters or more), should it appear
  in some other form.

A masked value reads ``***``; everything else is left as it was, so that a redacted command, config or URL still
says what it was. Redacting twice changes nothing, which is also how :func:`find_secrets` (the check of
``scripts/publish_results.sh``) tells that a record still holds something secret: redaction would change it.

This module sits in ``sb3_td3x.common`` because both the experiment runner and the sweeps write records through
it, and it imports nothing of the package (SQLAlchemy only when a URL with a password is met).

``python -m sb3_td3x.common.redaction FILE...`` exits with status 3 (``FOUND``), naming the file and line, when one
of the files holds something that looks like a secret; 2 when a file cannot be read. Not 1: that is what Python
exits with on an uncaught error, which a caller must not take for a finding.
"""

from __future__ import annotations

import functools
import logging
import os
import re
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar
from urllib.parse import quote, quote_plus

__all__ = ["MASK", "find_secrets", "is_secret_name", "redact", "redact_log_records"]

#: What a secret is replaced with (SQLAlchemy's mask for a URL's password).
MASK = "***"

T = TypeVar("T")

# Values that hold no secret: already masked (this module's mask, or the older "<redacted>" of config.yaml), or empty.
_NOT_SECRET = {MASK, "<redacted>", "", "null", "None", "~", "''", '""'}
# A placeholder such as <password> in a documented command.
_PLACEHOLDER = re.compile(r"<[\w .\-]*>")
# Words that make a name secret wherever they stand in it (api_token, db_password, secret_value).
_SECRET_WORDS = {"password", "passwd", "passphrase", "secret", "token", "apikey", "credential", "credentials"}
# Endings of a name written without separators (dbpassword, wandbapikey, awssecretaccesskey).
_SECRET_ENDINGS = ("password", "passwd", "secret", "token", "apikey", "accesskey", "secretkey", "privatekey")
# Environment values shorter than this are not masked where they appear verbatim (they would match ordinary words).
_MIN_LITERAL = 8

# A name as it appears before '=' or ':' (dotted config paths, Hydra's +/~ prefixes, environment variables).
_NAME = r"[A-Za-z_][\w.\-]*"
# A value: quoted, or up to whitespace, a quote or '&' (the next field of a URL query string).
_VALUE = r"""(?:'[^'\n]*'|"(?:[^"\\\n]|\\.)*"|[^\s'"&]+)"""
_URL = re.compile(r"""[A-Za-z][\w+.\-]*://[^\s'"`]+""")
_ASSIGNMENT = re.compile(rf"(?<![\w.\-+~])(?P<prefix>[+~]{{0,2}})(?P<name>{_NAME})(?P<sep>=)(?P<value>{_VALUE})")
_OPTION = re.compile(rf"(?<![\w\-])(?P<prefix>--?)(?P<name>[A-Za-z][\w\-]*)(?P<sep>[ \t]+|=)(?P<value>{_VALUE})")
_QUOTED_KEY = re.compile(  # "name": value in JSON, 'name': value in a Python repr; an unquoted value ends at , } ]
    rf"""(?P<prefix>(?P<quote>["']))(?P<name>{_NAME})(?P=quote)(?P<sep>\s*:\s*)"""
    rf"""(?P<value>'[^'\n]*'|"(?:[^"\\\n]|\\.)*"|[^\s,}}\]]+)"""
)
_YAML_KEY = re.compile(rf"(?m)^(?P<prefix>[ \t]*(?:-[ \t]+)?)(?P<name>{_NAME})(?P<sep>:[ \t]+)(?P<value>[^\n]*?)[ \t]*$")
_TRAILING = ".,;:)]}>"


@functools.lru_cache(maxsize=4096)
def is_secret_name(name: str) -> bool:
    """Whether a value under ``name`` is a secret: a name ending in ``key``, ``token``, ``password``, ``secret``
    (``WANDB_API_KEY``, ``env.kwargs.api_key``, ``--api-key``, ``PGPASSWORD``), or holding ``password``, ``secret``,
    ``token`` or ``credentials`` as a word (``db_password_hash``). ``max_tokens``, ``norm_obs_keys`` and ``PWD`` are
    not secret."""
    last = re.split(r"[.]", name.lstrip("+~-"))[-1]
    spaced = re.sub(r"([a-z0-9])([A-Z])", r"\1_\2", last)  # apiKey -> api_Key
    words = [word.lower() for word in re.split(r"[^A-Za-z0-9]+", spaced) if word]
    if not words:
        return False
    joined = "".join(words)
    return words[-1] == "key" or bool(_SECRET_WORDS.intersection(words)) or joined.endswith(_SECRET_ENDINGS)


def redact(value: T) -> T:
    """``value`` with its secrets replaced by ``***`` (see the module docstring); it is not modified in place.

    :param value: text (a command line, a log line, a URL, a file's content), a mapping (a config, an environment:
        the value under a secret-like key is masked whatever it is, other values are redacted in turn), a list or
        tuple (an argv: each item, and the item after a secret-like option such as ``--password``), or anything
        else, returned as it is
    """
    if isinstance(value, str):
        return _redact_text(value)  # type: ignore[return-value]
    if isinstance(value, Mapping):
        return {  # type: ignore[return-value]
            key: (_mask_value(item) if isinstance(key, str) and is_secret_name(key) else redact(item))
            for key, item in value.items()
        }
    if isinstance(value, (list, tuple)):
        items = list(value)
        out = []
        for index, item in enumerate(items):
            previous = items[index - 1] if index else None
            after_option = isinstance(previous, str) and re.fullmatch(r"--?[A-Za-z][\w\-]*", previous) is not None
            if after_option and is_secret_name(previous) and isinstance(item, str) and _is_value_secret(item):
                out.append(MASK)
            else:
                out.append(redact(item))
        return tuple(out) if isinstance(value, tuple) else out  # type: ignore[return-value]
    return value


def _mask_value(value: Any) -> Any:
    return None if value is None else MASK


def _redact_text(text: str) -> str:
    if not text:
        return text
    for literal in _environment_secrets():
        if literal in text:
            text = text.replace(literal, MASK)
    if "://" in text:
        text = _URL.sub(lambda m: _redact_url(m.group(0)), text)
    if "=" in text:
        text = _ASSIGNMENT.sub(_mask_match, text)
    if "-" in text:
        text = _OPTION.sub(_mask_match, text)
    if ":" in text:
        text = _QUOTED_KEY.sub(_mask_match, text)
        text = _YAML_KEY.sub(_mask_match, text)
    return text


def _is_value_secret(value: str) -> bool:
    bare = value.strip("'\"")
    return value not in _NOT_SECRET and bare not in _NOT_SECRET and _PLACEHOLDER.fullmatch(bare) is None


def _mask_match(match: re.Match[str]) -> str:
    value = match.group("value")
    if not is_secret_name(match.group("name")) or not _is_value_secret(value):
        return match.group(0)
    if value[0] in "'\"" and value[-1] == value[0] and len(value) > 1:
        quote_char = value[0]  # keep the quotes it had
    elif "quote" in match.re.groupindex:
        quote_char = match.group("quote")  # "password": 123 -> "password": "***", still JSON
    elif match.re is _YAML_KEY:
        quote_char = "'"  # an unquoted *** would be a YAML alias
    else:
        quote_char = ""
    start = match.start("value") - match.start(0)
    return match.group(0)[:start] + quote_char + MASK + quote_char


def _redact_url(token: str) -> str:
    """A URL with its password masked; unchanged when it has none (or it is masked already)."""
    if "@" not in token:
        return token
    stripped = token.rstrip(_TRAILING)
    trailing = token[len(stripped) :]
    before_query = stripped.split("?", 1)[0]
    if before_query.count("@") == 1:
        from sqlalchemy.engine import make_url

        try:
            url = make_url(stripped)
        except Exception:  # noqa: BLE001  (not a URL SQLAlchemy reads, e.g. a port that is not a number)
            url = None
        if url is not None:
            if url.password is None or not _is_value_secret(url.password):
                return token
            return url.render_as_string(hide_password=True) + trailing
    # SQLAlchemy cannot read it, or the password holds a raw '@': mask from the user's ':' to the last '@'.
    match = re.match(r"(?P<head>[^:]+://[^:/@]*:)(?P<password>.*)@(?P<tail>[^@]*)$", before_query, re.DOTALL)
    if match is None or not _is_value_secret(match.group("password")):
        return token
    return match.group("head") + MASK + "@" + stripped[match.end("password") + 1 :] + trailing


def _environment_secrets() -> list[str]:
    """The values of this process's secret-like environment variables, as written and URL-encoded, longest first."""
    values: set[str] = set()
    for name, value in os.environ.items():
        if len(value) >= _MIN_LITERAL and is_secret_name(name):
            values.update({value, quote(value, safe=""), quote_plus(value)})
    return sorted(values, key=len, reverse=True)


def find_secrets(text: str) -> list[tuple[int, str]]:
    """The lines of ``text`` that hold something secret, as ``(line number, the line redacted)``; none for a
    redacted record. What :func:`redact` would change is what looks secret."""
    found = []
    for number, line in enumerate(text.splitlines(), start=1):
        redacted = redact(line)
        if redacted != line:
            found.append((number, redacted.strip()))
    return found


class _RedactingRecordFactory:
    """Wraps the log record factory: every record's message (and traceback) is redacted when it is created, so
    every handler, including the ones Hydra configures later, writes it redacted."""

    def __init__(self, factory: Any) -> None:
        self.factory = factory

    def __call__(self, *args: Any, **kwargs: Any) -> logging.LogRecord:
        record = self.factory(*args, **kwargs)
        try:
            message = record.getMessage()
            redacted = redact(message)
            if redacted != message:
                record.msg, record.args = redacted, ()
            if record.exc_info and not record.exc_text:
                text = logging.Formatter().formatException(record.exc_info)
                record.exc_text = redact(text)
        except Exception:  # noqa: BLE001  (a record that cannot be formatted is logging's to report, as usual)
            pass
        return record


def redact_log_records() -> None:
    """Redact every log line of this process from now on (idempotent); called by ``run.py`` and the sweep command."""
    factory = logging.getLogRecordFactory()
    if not isinstance(factory, _RedactingRecordFactory):
        logging.setLogRecordFactory(_RedactingRecordFactory(factory))


FOUND = 3  # main's exit status when a file holds something that looks like a secret


def main(argv: list[str] | None = None) -> int:
    """``python -m sb3_td3x.common.redaction FILE...``: status ``FOUND`` (3), with one line per finding, when a file
    holds something that looks like a secret; 2 when a file cannot be read."""
    paths = [Path(arg) for arg in (sys.argv[1:] if argv is None else argv)]
    if not paths:
        print("usage: python -m sb3_td3x.common.redaction FILE...", file=sys.stderr)
        return 2
    status = 0
    for path in paths:
        try:
            text = path.read_text(errors="replace")
        except OSError as err:
            print(f"error: cannot read {path}: {err.strerror}", file=sys.stderr)
            return 2
        for number, line in find_secrets(text):
            print(f"{path}:{number}: looks like a secret (shown masked): {line[:300]}", file=sys.stderr)
            status = FOUND
    return status


if __name__ == "__main__":
    raise SystemExit(main())
