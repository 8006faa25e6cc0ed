"""The offline path: measured runs in, fitted models and reports out.

Nothing here runs in the compensation loop. The live path is drivers → runtime →
write-back → outputs (``gateway.live.loop``, ``gateway.live.writeback``,
``gateway.outputs.sinks``); this package holds the front ends of the commands that
work on recorded data:

- :mod:`gateway.offline.export`: logged points (InfluxDB or the local store) →
  measured-run CSV (``export``);
- :mod:`gateway.offline.tables`: the plain-text accuracy tables of ``fit``;
- :mod:`gateway.offline.report`: the plots and HTML page of
  ``analyze --report``.

The maths itself lives in :mod:`models`. These modules import heavy libraries
(matplotlib, jinja2) at module level, so the CLI imports them only inside the
commands that use them.
"""
