"""A test centre's archive: many recordings identified and diagnosed on a Dask cluster, into one table.

* :mod:`~online_id.archive.runner` -- map a function over items on a Dask
  cluster (local or a scheduler's address), failures as outcomes;
* :mod:`~online_id.archive.metadata` -- a recording's bench and start time;
* :mod:`~online_id.archive.table` -- the table's columns and rows (no I/O);
* :mod:`~online_id.archive.store` -- the table on disk (Parquet, CSV);
* :mod:`~online_id.archive.recording` -- the tasks on one recording;
* :mod:`~online_id.archive.batch` -- an archive run (what is new, the tasks, the rows);
* :mod:`~online_id.archive.trend` -- drift per bench and operating point (no I/O);
* :mod:`~online_id.archive.simulated` -- a simulated archive written as MDF 4.

Dask and pyarrow (the ``archive`` extra) are imported only where they are used.
"""
