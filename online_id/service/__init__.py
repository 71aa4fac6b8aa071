"""The streaming path shared by the live service and replay: frames assembled into samples (``assembly``),
the pipeline (``pipeline``: recursive identification, tracking, detection, publication), its runtime
(``runtime``: frames in, frames out), the worker process and its scheduling (``offload``, ``scheduling``),
commands and their freshness (``commands``), state restored at start (``restore``), the reaction-time
figures (``reaction``) and the live receive loop on a CAN bus (``live``)."""
