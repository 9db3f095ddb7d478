"""The pure core: camera model, spectrum, lattice, plane, estimator, filter and their results.

Arrays and plain values in, frozen dataclasses out. Nothing here reads a clock, a file handle
or a socket, and nothing here imports `drivers` or the application around it (the import
contracts in pyproject.toml enforce that).
"""
