"""The live daemon (``bmsid run``): the pipeline is :class:`bmsid.daemon.core.Daemon`.

Modules: ``sources`` (CAN in), ``core`` (frames -> samples -> bank -> publishers), ``canout``
(CAN output schedule), ``checkpoint``, ``sdnotify``, ``watchdog`` (when to feed systemd's
watchdog), ``demo_data`` (the bundled demo log).
``core`` is not imported here: it loads the estimator stack, which light commands do not need.
"""
