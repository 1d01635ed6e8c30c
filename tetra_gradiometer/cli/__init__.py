"""The command line: ``python -m tetra_gradiometer COMMAND`` (one module per command).

A command parses its arguments, calls a pipeline and a report, and prints one ``error:``
line for a :class:`~tetra_gradiometer.errors.TetraError`. ``fleet`` is ``batch``'s task per
bag (calibrate, compensate, discrepancy and their reports), importable by a Dask worker.
The top layer: nothing else in the package imports ``cli``.
"""
