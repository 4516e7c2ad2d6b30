"""The framework layer: errors, containers, the stage protocol, geometry, configuration, files.

Imports nothing else of the project (docs/architecture.md, ``tests/test_layers.py``).
"""
