"""Offline identification and fitting as a library (``bmsid.cli`` only parses and prints).

- ``inputs``: recordings (tester CSV, candump log) opened as sources of sample blocks; cell
  configs; the shared option parsers.
- ``identify``: :func:`~bmsid.offline.identify.identify_file`, one call per input, set up by a
  picklable ``IdentifySpec``; blocks in, the bank, estimate blocks out.
- ``scoring``: the evaluation window, the run's result and its Eq. 31 metrics.
- ``outputs`` / ``writers`` / ``plots``: metrics.json, params.csv (appended per block), figures
  and report lines.
- ``ocv_config`` (files in, cell config out) over ``ocv_fit`` (the numeric OCV fit);
  ``report``: Table 2 and the consistency analysis of ``bmsid compare``; ``csvio``: the loaders.
"""
