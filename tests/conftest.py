"""Test configuration: single-threaded BLAS (small matrices; two cores shared with numba)."""

import os

import pytest

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")


@pytest.fixture
def cli_error(capsys):
    """Run ``online-id ARGV``; expect exit status 2 and return its error, one line without a traceback."""
    from online_id.cli import main

    def run(argv: list[str]) -> str:
        capsys.readouterr()
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("error: ") and "\n" not in err and "Traceback" not in err
        return err

    return run
