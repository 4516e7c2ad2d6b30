"""magalign framework: recording model, stage protocol, runner, configuration, CLI, errors."""

__version__ = "0.1.0"
