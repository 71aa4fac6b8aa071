"""How a chain case is written down, as users have their files: drawn from the case's seed.

- ``bench``: one CSV in the layout ``online-id diagnose`` reads, with the user's own column names,
  units (time in s or ms; speeds in rpm or rad/s, or cumulative angles in deg or rad), torque sign,
  extra columns and column order, named in a config YAML; sometimes a recorded test-torque demand.
- ``rig``: two loggers on one clock that start about a second apart, each with jittered sample
  instants: a drive file (time, drive and load torque set-points and measurements) and a sensor file
  (time, cumulative encoder angles in degrees or in encoder counts, shaft torques).
"""

from __future__ import annotations

import numpy as np

from online_id.evaluation import chain_plant as cc

_BENCH_NAMES = (
    {"engine_speed": "engine_speed", "dyno_speed": "dyno_speed", "dyno_torque": "dyno_torque",
     "demand": "prbs_demand", "extra": ("oil_temp_c", "speed_setpoint", "throttle_pct")},
    {"engine_speed": "N_Motor", "dyno_speed": "N_Bremse", "dyno_torque": "Md_Bremse",
     "demand": "Md_Anregung", "extra": ("T_Oel", "N_Soll", "Alpha")},
    {"engine_speed": "EngSpd", "dyno_speed": "DynoSpd", "dyno_torque": "DynoTrq",
     "demand": "TrqDemand", "extra": ("OilTemp", "SpdSetpoint", "Pedal")},
    {"engine_speed": "crank speed", "dyno_speed": "brake speed", "dyno_torque": "brake torque",
     "demand": "test torque", "extra": ("coolant temp", "speed set point", "lambda")},
)
_TIME_NAMES = {"s": ("time", "t", "Time_s", "timestamp"), "ms": ("time_ms", "t_ms", "Zeit_ms", "millis")}
_SPEED_SUFFIX = {"rpm": ("_rpm", " [rpm]", ""), "rad/s": ("_rads", " [rad/s]", ""), "deg": ("_deg", " [deg]", ""),
                 "rad": ("_rad", " [rad]", "")}


def _pick(rng: np.random.Generator, seq):
    return seq[int(rng.integers(len(seq)))]


def draw_bench_files(rng: np.random.Generator, spec: dict) -> dict:
    """The file layout of a bench case (see module notes)."""
    style = _pick(rng, _BENCH_NAMES)
    time_unit = "ms" if rng.random() < 0.3 else "s"
    speed_unit = _pick(rng, ("rpm",) * 6 + ("rad/s",) * 2 + ("deg", "rad"))
    suffix = _pick(rng, _SPEED_SUFFIX[speed_unit])
    cols = {"time": _pick(rng, _TIME_NAMES[time_unit]),
            "engine_speed": style["engine_speed"] + suffix, "dyno_speed": style["dyno_speed"] + suffix,
            "dyno_torque": style["dyno_torque"]}
    extras = [style["extra"][i] for i in sorted(rng.choice(3, size=int(rng.integers(0, 3)), replace=False))]
    demand = style["demand"] if rng.random() < 0.3 else None
    order = [cols["time"]] + [str(c) for c in rng.permutation(
        [cols["engine_speed"], cols["dyno_speed"], cols["dyno_torque"]] + extras + ([demand] if demand else []))]
    angle = speed_unit in ("deg", "rad")
    files = {
        "layout": "bench", "csv": "bench.csv", "config": "bench.yaml", "columns": cols, "order": order,
        "extras": extras, "demand": demand, "time_unit": time_unit, "speed_unit": speed_unit,
        "time_offset_s": 0.0 if rng.random() < 0.5 else float(round(rng.uniform(10.0, 5000.0), 3)),
        "torque_sign": "braking" if rng.random() < 0.7 else "driving",
        "pulses_per_rev_in": "config" if rng.random() < 0.5 else "option",
        "speed_noise_rpm": cc.logu(rng, 0.02, 0.2),
        "speed_step": float(_pick(rng, (1e-4, 1e-3) if speed_unit == "deg" else (2e-6, 2e-5) if angle else
                                  (0.01, 0.02, 0.05, 0.1) if speed_unit == "rpm" else (0.001, 0.005, 0.01))),
        "torque_noise_nm": float(rng.uniform(0.1, 0.5)), "torque_step_nm": float(_pick(rng, (0.01, 0.02, 0.05, 0.1))),
        "shaft_columns": {"engine": [cols["engine_speed"]], "dyno": [cols["dyno_speed"]]},
    }
    if spec["kind"] == "sensor_delay":
        sig = spec["effect"]["signal"]
        files["delay_names"] = [sig, cols[sig]]
    return files


_RIG_STYLES = (
    {"time": ("time", "time"), "drive_set": "drive torque setpoint", "drive_meas": "drive torque",
     "load_set": "load torque setpoint", "load_meas": "load torque", "encoder": "{ordinal} encoder",
     "torque": "shaft torque {k}"},
    {"time": ("t_s", "t_s"), "drive_set": "T_drive_ref", "drive_meas": "T_drive", "load_set": "T_load_ref",
     "load_meas": "T_load", "encoder": "enc{k}", "torque": "T_shaft{k}"},
    {"time": ("Time [s]", "Timestamp [s]"), "drive_set": "M_soll_Antrieb", "drive_meas": "M_ist_Antrieb",
     "load_set": "M_soll_Last", "load_meas": "M_ist_Last", "encoder": "Winkel{k}", "torque": "Md_Welle{k}"},
)
_ORDINALS = ("first", "second", "third", "fourth", "fifth", "sixth")


def draw_rig_files(rng: np.random.Generator, spec: dict) -> dict:
    """The file layout of a rig case (see module notes)."""
    style = _pick(rng, _RIG_STYLES)
    fs = spec["fs_hz"]
    sensor_rate = fs if rng.random() < 0.75 else float(_pick(rng, [r for r in (fs / 2, 2 * fs) if r >= 500]))
    measured = [i for i, e in enumerate(spec["elements"]) if e["measured"]]
    encoders = []
    for k, i in enumerate(measured):
        counts = rng.random() < 0.3
        cpr = int(_pick(rng, (8192, 16384, 20000, 32768, 65536)))
        name = style["encoder"].format(ordinal=_ORDINALS[k], k=k + 1)
        encoders.append({"element": i, "shaft": spec["elements"][i]["name"], "column": name + (
            "" if style["encoder"].startswith("{") else " [counts]" if counts else " [deg]"),
                         "unit": f"counts{cpr}" if counts else "deg", "cpr": cpr})
    n_torques = int(rng.integers(1, min(3, len(spec["joints"])) + 1))
    joints = sorted(int(j) for j in rng.choice(len(spec["joints"]), size=n_torques, replace=False))
    torques = [{"joint": j, "column": style["torque"].format(k=n + 1)} for n, j in enumerate(joints)]
    files = {
        "layout": "rig", "drive": "drive.csv", "sensor": "sensor.csv",
        "drive_time": style["time"][0], "sensor_time": style["time"][1],
        "drive_columns": {k: style[k] for k in ("drive_set", "drive_meas", "load_set", "load_meas")},
        "encoders": encoders, "shaft_torques": torques, "drive_rate_hz": fs, "sensor_rate_hz": sensor_rate,
        "drive_jitter_s": cc.logu(rng, 5e-6, 50e-6), "sensor_jitter_s": cc.logu(rng, 5e-6, 50e-6),
        "sensor_start_s": float((1 if rng.random() < 0.7 else -1) * rng.uniform(0.5, 1.5)),
        "drive_tail_s": float(rng.uniform(0.2, 1.5)), "sensor_tail_s": float(rng.uniform(0.2, 1.5)),
        "clock_origin_s": 0.0 if rng.random() < 0.5 else float(round(rng.uniform(100.0, 80000.0), 3)),
        "input": "drive_set" if rng.random() < 0.5 else "drive_meas",
        "torque_noise_nm": 0.01 * spec["prbs"]["amplitude_nm"] * float(rng.uniform(0.5, 2.0)),
        "torque_step_nm": float(_pick(rng, (0.001, 0.01))),
        "shaft_columns": {e["shaft"]: [e["column"]] for e in encoders},
    }
    files["output_column"] = encoders[0]["column"]
    if spec["kind"] == "sensor_delay":
        if spec["effect"]["signal"] == "output":
            files["delay_names"] = [encoders[0]["column"], encoders[0]["shaft"]]
        else:
            files["delay_names"] = [files["drive_columns"][files["input"]]]
    return files
