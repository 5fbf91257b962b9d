"""Offline identification and fitting as a library (``bmsid.cli`` only parses and prints).

- ``inputs``: recordings (tester CSV, candump log) opened as sources of sample blocks, read
  from their files in pieces; cell configs; the shared option parsers.
- ``identify``: :func:`~bmsid.offline.identify.identify_file`, one call per input, set up by a
  picklable ``IdentifySpec``; blocks in, the bank, estimate blocks out (kept, or streamed).
- ``scoring``: the evaluation window, the run's result and its Eq. 31 metrics, scored block by
  block (``RunScorer``) over ``accumulate``'s running sums and plot decimation.
- ``outputs`` / ``writers`` / ``plots``: metrics.json, params.csv or params.parquet (appended
  per block, every tick or per ``--every`` interval), figures and report lines.
- ``ocv_config`` (files in, cell config out) over ``ocv_fit`` (the numeric OCV fit);
  ``report``: Table 2 and the consistency analysis of ``bmsid compare``; ``csvio``: the loaders.
"""
