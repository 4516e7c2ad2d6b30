"""Configuration files (scenarios, campaigns): TOML as data, never code.

:class:`TomlDoc` wraps a parsed TOML file so that every validation error names the file, the
dotted key and the line it is on (``tomllib`` does not keep positions, so lines are found by
scanning the text for the table header and the key).
"""

from __future__ import annotations

import enum
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import tomllib

from pipeline.core.errors import ConfigError

E = TypeVar("E", bound=enum.Enum)
_MISSING = object()


@dataclass(frozen=True)
class TomlDoc:
    """A parsed TOML document that can point at its own lines.

    Attributes
    ----------
    path : str
    data : dict
    text : str

    """

    path: str
    data: dict[str, Any]
    text: str

    @classmethod
    def load(cls, path: str | Path) -> TomlDoc:
        """Read and parse ``path``; syntax errors become :class:`ConfigError` with the line."""
        p = Path(path)
        try:
            text = p.read_text(encoding="utf-8")
        except OSError as exc:
            raise ConfigError(f"cannot read: {exc.strerror}", path=p) from exc
        except UnicodeDecodeError as exc:
            raise ConfigError("not a UTF-8 text file", path=p) from exc
        return cls.parse(text, str(p))

    @classmethod
    def parse(cls, text: str, path: str = "<string>") -> TomlDoc:
        """Parse TOML text."""
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            m = re.search(r"line (\d+)", str(exc))
            raise ConfigError(
                f"not valid TOML: {exc}", path=path, line=int(m.group(1)) if m else None
            ) from exc
        return cls(path, data, text)

    def line_of(self, key: str) -> int | None:
        """Best-effort 1-based line of a dotted key (``a.b.c`` or ``a[2].b``)."""
        parts = [p for p in re.split(r"\.|\[\d+\]", key) if p]
        if not parts:
            return None
        lines = self.text.splitlines()
        leaf = re.escape(parts[-1])
        table = ".".join(parts[:-1])
        start = 0
        if table:
            pat = re.compile(r"^\s*\[\[?\s*" + re.escape(table) + r"\s*\]\]?\s*$")
            for i, ln in enumerate(lines):
                if pat.match(ln):
                    start = i
                    break
        pat_key = re.compile(r"^\s*(" + leaf + r'|"' + leaf + r'")\s*=')
        for i in range(start, len(lines)):
            if pat_key.match(lines[i]):
                return i + 1
        pat_tab = re.compile(r"^\s*\[\[?\s*" + re.escape(".".join(parts)) + r"\s*\]\]?\s*$")
        for i, ln in enumerate(lines):
            if pat_tab.match(ln):
                return i + 1
        return None

    def error(self, key: str, message: str, hint: str | None = None) -> ConfigError:
        """Return a :class:`ConfigError` naming this file, ``key`` and its line."""
        return ConfigError(message, path=self.path, key=key, line=self.line_of(key), hint=hint)

    def get(self, key: str, default: Any = _MISSING, *, table: Mapping | None = None) -> Any:
        """Value at dotted ``key``; without a default a missing key is an error."""
        cur: Any = self.data if table is None else table
        for part in key.split("."):
            if isinstance(cur, Mapping) and part in cur:
                cur = cur[part]
            elif default is _MISSING:
                raise self.error(key, "is required but missing")
            else:
                return default
        return cur

    def number(self, key: str, default: Any = _MISSING, *, lo: float | None = None,
               hi: float | None = None, table: Mapping | None = None) -> float:
        """Return a real number within ``[lo, hi]``."""
        v = self.get(key, default, table=table)
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise self.error(key, f"must be a number, got {v!r}")
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise self.error(key, f"must be within [{lo}, {hi}], got {v}")
        return float(v)

    def vector(self, key: str, n: int = 3, default: Any = _MISSING, *,
               table: Mapping | None = None) -> list[float]:
        """Return a list of ``n`` numbers."""
        v = self.get(key, default, table=table)
        if not isinstance(v, list) or len(v) != n or not all(
            isinstance(x, int | float) and not isinstance(x, bool) for x in v
        ):
            raise self.error(key, f"must be a list of {n} numbers, got {v!r}")
        return [float(x) for x in v]

    def choice(self, key: str, enum_type: type[E], default: Any = _MISSING, *,
               table: Mapping | None = None) -> E:
        """Return a value of ``enum_type`` spelled as its value."""
        v = self.get(key, default, table=table)
        if isinstance(v, enum_type):
            return v
        try:
            return enum_type(v)
        except ValueError:
            allowed = ", ".join(str(e.value) for e in enum_type)
            raise self.error(key, f"must be one of {allowed}, got {v!r}") from None

    def check_keys(self, table: Mapping, allowed: set[str], prefix: str = "") -> None:
        """Refuse unknown keys (a typo must not be silently ignored)."""
        for k in table:
            if k not in allowed:
                key = f"{prefix}.{k}" if prefix else k
                raise self.error(key, f"unknown key (allowed: {', '.join(sorted(allowed))})")
