"""``--dask`` and ``--scheduler`` of the commands whose cases can run as Dask tasks (needs the archive extra)."""

from __future__ import annotations

import argparse


def add_dask_options(p: argparse.ArgumentParser, failed: str) -> None:
    """The two exclusive options; ``failed`` says what becomes of a case whose task fails."""
    d = p.add_mutually_exclusive_group()
    d.add_argument("--dask", action="store_true",
                   help="run the cases as Dask tasks on a local cluster of --jobs worker processes (needs the "
                        "archive extra); the results are those of the process pool")
    d.add_argument("--scheduler", metavar="tcp://HOST:8786",
                   help=f"run the cases as Dask tasks on this scheduler's workers (a cluster); {failed}")
