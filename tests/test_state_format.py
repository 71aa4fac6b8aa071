"""The state document keeps its format: a state file saved by the release before the pipeline's parts were
split (``tests/data/state_v1.json``: a run with backlash, a learned engaged flank, held and learned cells,
reference windows and a latched fault) loads, and is saved again unchanged."""

import json
from pathlib import Path

from online_id.config import Settings
from online_id.io.statefile import _plain, load_state
from online_id.service.persistence import STATE_VERSION
from online_id.service.pipeline import Pipeline
from online_id.service.restore import restore_pipeline

SAVED = Path(__file__).parent / "data" / "state_v1.json"


def _doc(state: dict) -> dict:
    """``state`` as its file holds it (JSON numbers, lists)."""
    return json.loads(json.dumps(_plain(state), allow_nan=True))


def test_a_saved_state_is_restored_and_saved_again_unchanged():
    saved = load_state(SAVED)
    assert saved["version"] == STATE_VERSION
    pipe = Pipeline(Settings())
    pipe.load_state(saved)
    assert _doc(pipe.get_state()) == _doc(saved)
    assert pipe.baseline.nonlinear and pipe.engaged.summary()["usable"]
    assert pipe.detector.active is not None and pipe.detector.active.level == 2
    assert [a.kind.name for a in pipe.alerts] == ["FREQ_DRIFT", "FREQ_DRIFT"]


def test_a_saved_state_starts_a_new_run_with_its_baselines_and_a_fresh_estimator():
    saved = load_state(SAVED)
    pipe = Pipeline(Settings())
    pipe.load_state(saved, new_run=True)
    got, fresh = _doc(pipe.get_state()), _doc(Pipeline(Settings()).get_state())
    for key in ("baseline", "references", "windows", "engaged", "alerts"):
        assert got[key] == _doc(saved)[key], key
    assert got["estimator"] == fresh["estimator"] and got["tracker"] == fresh["tracker"]
    assert got["healthy_rpm"] is None and pipe.detector.active is not None


def test_the_service_restores_a_saved_state(tmp_path):
    said = []
    pipe = restore_pipeline(SAVED, Settings(), said.append)
    assert pipe is not None, said
    assert _doc(pipe.get_state()) == _doc(load_state(SAVED))


def test_relearn_from_a_log_forgets_what_the_relearn_command_forgets(tmp_path, capsys):
    """``relearn --from LOG`` learns into a state whose baselines, reference solutions and windows and engaged
    flank are all gone first (a repaired shaft must not be rechecked against the old one's windows)."""
    import shutil

    from online_id.cli import main
    from online_id.offline.replay import state_file

    state_dir = tmp_path / "state"
    state_dir.mkdir()
    shutil.copy(SAVED, state_file(state_dir))
    cfg = tmp_path / "short.yaml"
    cfg.write_text("operating_points: [{speed_rpm: 1500, duration_s: 3}]\nseed: 4\n")
    log = tmp_path / "short.log"
    assert main(["simulate", "--config", str(cfg), "--out", str(tmp_path / "s.csv"), "--can-log", str(log)]) == 0
    assert main(["relearn", "--from", str(log), "--state", str(state_dir)]) == 0
    assert "0 cells learned" in capsys.readouterr().out
    after = load_state(state_file(state_dir))
    commanded = Pipeline(Settings())
    commanded.load_state(load_state(SAVED))
    commanded.on_command(2, 0.0)  # RELEARN
    for key in ("references", "windows", "engaged"):
        assert _doc(after)[key] == _doc(commanded.get_state())[key], key
    assert not after["references"] and not after["windows"] and not after["engaged"]["learned"]
