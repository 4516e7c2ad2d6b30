"""The one exception tree of magalign.

Every error carries its context (the file, the key, the stage) and says what to do. Library code
raises these; only the CLI turns them into exit codes and a single line on stderr
(CONVENTIONS: exit 2 for bad input or usage, 1 for a regression, 3 for a partly failed campaign).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any


class MagalignError(Exception):
    """Base of every error magalign raises on purpose.

    Parameters
    ----------
    message : str
        What is wrong, in words a survey user understands.
    path : str or Path, optional
        The file the problem is in; named first in the one-line message.
    hint : str, optional
        What to do about it.

    """

    exit_code: int = 2

    def __init__(self, message: str, *, path: str | Path | None = None, hint: str | None = None):
        self.message = message
        self.path = None if path is None else str(path)
        self.hint = hint
        super().__init__(self.one_line())

    def naming(self, path: str | Path | None) -> MagalignError:
        """Name ``path`` as the file of an error raised without one; returns ``self``.

        A stage deep in the pipeline may not know which file its data came from; the
        command (or the campaign worker) that read it does, and every error line names one.
        """
        if self.path is None and path is not None and not self.message.startswith(str(path)):
            self.path = str(path)
            self.args = (self.one_line(),)
        return self

    def one_line(self) -> str:
        """Return the single line the CLI prints: ``file: problem (what to do)``."""
        head = f"{self.path}: " if self.path else ""
        tail = f" ({self.hint})" if self.hint else ""
        return f"{head}{self.message}{tail}"


class InputError(MagalignError):
    """A recording or input file cannot be used as it is (exit status 2)."""


class NotMcapError(InputError):
    """The file is not an MCAP recording (bad magic, empty, cut inside the header)."""


class CorruptRecordingError(InputError):
    """The MCAP structure is damaged beyond what can be recovered."""


class ChannelError(InputError):
    """A magnetometer or attitude channel is missing, ambiguous or of an unsupported type.

    Parameters
    ----------
    role : str, optional
        ``"magnetometer"`` or ``"attitude"``: the role that could not be filled.

    """

    def __init__(self, message: str, *, role: str | None = None, **kw):
        self.role = role
        super().__init__(message, **kw)


class SchemaError(InputError):
    """A message schema is unknown or its layout cannot be decoded."""


class DataQualityError(InputError):
    """The values in a recording cannot be trusted (wrong unit, NaN, stuck sensor, ...)."""


class ConfigError(MagalignError):
    """A configuration, scenario or campaign file is wrong.

    Parameters
    ----------
    key : str, optional
        Dotted key of the offending entry.
    line : int, optional
        1-based line number in the file.

    """

    def __init__(
        self,
        message: str,
        *,
        path: str | Path | None = None,
        key: str | None = None,
        line: int | None = None,
        hint: str | None = None,
    ):
        self.key = key
        self.line = line
        where = ""
        if line is not None:
            where += f"line {line}: "
        if key is not None:
            where += f"key '{key}': "
        super().__init__(where + message, path=path, hint=hint)


class UsageError(MagalignError):
    """The command line is wrong (exit status 2)."""


class PipelineBuildError(MagalignError):
    """Stages of a pipeline do not fit together; raised before any file is read.

    Parameters
    ----------
    stage : str
        Name of the stage whose requirements are not provided.
    missing : tuple of str
        The context fields it requires that no earlier stage provides.

    """

    def __init__(self, stage: str, missing: tuple[str, ...], available: tuple[str, ...]):
        self.stage = stage
        self.missing = missing
        super().__init__(
            f"stage {stage} requires {', '.join(missing)}, which no earlier stage provides "
            f"(available: {', '.join(available) or 'nothing'})",
            hint="put a stage that provides it earlier in the pipeline",
        )


class EstimationError(MagalignError):
    """The estimator cannot produce a trustworthy result from these data."""


class NotObservableError(EstimationError):
    """The motion in the recording cannot determine what was asked for."""


class RefusedError(EstimationError):
    """The fit's checks refused the result.

    Start-dependent, or the model does not describe the data; the message gives the reason
    and what motion or model is missing.
    """


class OutputError(MagalignError):
    """An output cannot be written (disk full, path escaping the output folder, ...)."""


class RegressionFailure(MagalignError):
    """Results differ from the baseline beyond tolerance (exit status 1)."""

    exit_code = 1


class CampaignPartialFailure(MagalignError):
    """A campaign finished but some recordings failed (exit status 3)."""

    exit_code = 3

    def __init__(self, failures: list[tuple[str, str]]):
        self.failures = failures
        lines = "; ".join(f"{name}: {why}" for name, why in failures)
        super().__init__(f"{len(failures)} recording(s) failed: {lines}")


class RecoveredDataWarning(UserWarning):
    """A damaged recording was read as far as it is intact; the message says what was lost."""


class QuestionableCalibrationWarning(UserWarning):
    """A calibration whose verdict is QUESTIONABLE is used or exported; the message says why."""


def damage_behind(caught: Iterable[Any], path: str | None = None) -> str:
    """Return the recovered damage among caught warnings, to add to a failure's line.

    ``caught``: :class:`warnings.WarningMessage` records. A failing command's other
    warnings are moot, but data lost to damage may be why it failed (a file cut off before
    its magnetometer channel: "no magnetometer channel found"). "" when there was none.
    """
    lost: list[str] = []
    for w in caught:
        if not issubclass(w.category, RecoveredDataWarning):
            continue
        text = str(w.message)
        if path and text.startswith(f"{path}: "):
            text = text[len(path) + 2:]  # the line names the file already
        if text not in lost:
            lost.append(text)
    return f"; the file was damaged: {'; '.join(lost)}" if lost else ""
