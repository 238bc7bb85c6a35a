"""Sinks: they observe a run and never change it.  The metrics row and table (``metrics``), the
rerun recording (``rerun_sink``; rerun is imported only when logging is on), the run folder's
result files written atomically (``files``) and the progress bar (``progress``)."""
