"""Test configuration: single-threaded BLAS (small matrices; two cores shared with numba)."""

import os

import pytest

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")


@pytest.fixture(autouse=True)
def _environment_as_it_was():
    """Put back the process environment after each test. A Dask ``LocalCluster``'s nannies write their workers'
    pre-spawn variables into the calling process (``PYTHONHASHSEED``, and with Dask's default configuration
    ``MALLOC_TRIM_THRESHOLD_=65536``, which ``archive.runner.cluster`` unsets): left there, every process a later
    test starts in this pytest worker would inherit them."""
    before = dict(os.environ)
    yield
    if os.environ != before:
        os.environ.clear()
        os.environ.update(before)


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


# Modules whose tests take longest in all (CPU seconds per module of the native tier, docs/testing.md), longest
# first. Only the order of the run depends on this list: a module missing from it runs in its usual place.
HEAVY_FIRST = ("test_detection_learning", "test_diagnose_bench", "test_linearity", "test_reference",
               "test_archive_evaluate", "test_detection_e2e", "test_window", "test_detection_damping_learning",
               "test_archive", "test_engaged_flank", "test_rig", "test_diagnose_channels", "test_cli",
               "test_identification", "test_service", "test_hardening_signals", "test_diagnose_joints",
               "test_hardening_time", "test_sysid_uncertainty", "test_engaged_resonance", "test_offload",
               "test_hardening_soak", "test_diagnose")


def pytest_collection_modifyitems(config, items):
    """On several workers (pytest-xdist, ``--dist loadscope --no-loadscope-reorder`` as ``make test`` runs it:
    a module's tests on one worker, so its module fixtures and caches are made once), the heaviest modules come
    first (``HEAVY_FIRST``), the rest in their usual order: each worker takes the next module when it is done
    with its own, so the long end-to-end modules start early and the short ones fill the end, instead of a long
    module starting last beside an idle worker."""
    argv = getattr(config, "workerinput", {}).get("mainargv", [])  # (a worker sees the run's --dist only there)
    if not any(a.endswith(("loadscope", "loadgroup")) for a in argv):
        return  # (the default --dist load hands out long slices of the list: the heavy modules would share one)
    rank = {name: i for i, name in enumerate(HEAVY_FIRST)}
    first: dict[str, int] = {}
    for i, item in enumerate(items):
        first.setdefault(item.nodeid.split("::")[0], i)

    def key(item):
        path = item.nodeid.split("::")[0]
        return rank.get(path.rsplit("/", 1)[-1].removesuffix(".py"), len(rank)), first[path]

    items.sort(key=key)
