"""magalign framework: recording model, stage protocol, runner, configuration, CLI, errors."""
from importlib.metadata import PackageNotFoundError, version

__version__ = "0.1.0"


def package_version() -> str:
    """Return the installed magalign version (package metadata), or "unknown"."""
    try:
        return version("magalign")
    except PackageNotFoundError:  # running from a source tree that was never installed
        return "unknown"
