"""The framework layer: errors, containers, the stage protocol, geometry, configuration, files.

Imports nothing else of the project (docs/architecture.md, ``tests/test_layers.py``). It also
holds the vocabulary (:mod:`pipeline.core.vocabulary`): the words the options are spelled in,
which every layer above names.
"""
