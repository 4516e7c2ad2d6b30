"""magalign stages: one module per stage, each a frozen dataclass with ``run(ctx) -> ctx``."""
