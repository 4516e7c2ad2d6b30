"""The file layer: MCAP reading and writing, CDR layouts, message encoders.

Imports ``pipeline.core`` and ``schemas`` only (docs/architecture.md, ``tests/test_layers.py``).
"""
