"""The program: the command line, one recording and campaigns, exports, simulation, papers.

The top layer: may import every other (docs/architecture.md, ``tests/test_layers.py``).
"""
