"""Write the simulated recordings of data/ (run from the project root:
``python data/make_simulated.py``); their true parameters are in the notes beside them.

Each is written the way another lab's logger would write it, so that importing and
fitting it exercises what a real recording needs, with a known answer:

- ``sim_logger_grasps.tsv``: a microcontroller logger. Tab-separated, CRLF, a comment
  line, millisecond stamps taken on arrival (+-0.3 ms jitter) at 333 Hz, one 0.5 s
  pause and 2 % of lines lost, force in grams on a sensor that reads 0.3 N with empty
  jaws, jaw angle in degrees (20 mm jaws), an extra status column, a truncated last
  line. Five grasps of a 4 mm thick liver-like tissue between free jaw motion.
- ``sim_stage_heavy.csv``: a positioning stage. Semicolons, a UTF-8 byte-order mark,
  units in the headers (s, N, mm), 500 Hz; 100 kg moving mass, forces to 200 N.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tissuecli.core.terms import Law
from tissuecli.core.tissue import DEFAULT_TISSUE, Tissue
from tissuecli.sim import loggers
from tissuecli.sim.synth import ForcepsModel, GraspingOperator, Operator, Sensors, synthesize

HERE = Path(__file__).resolve().parent
JAW_LENGTH_M = 0.020
THICKNESS_M = 0.004  # tissue between the tips: the jaws touch it 4 mm apart
OFFSET_N = 0.3


def logger_grasps(path: Path) -> None:
    rng = np.random.default_rng(2026)
    squeeze = Operator.random(rng)
    operator = GraspingOperator(squeeze=squeeze, grasp_s=3.0, free_s=1.2, ramp_s=0.3)
    sensors = Sensors(
        bits=16,
        force_noise_n=0.005,
        position_noise_m=5e-6,
        force_range_n=(-1.0, 5.0),
        position_range_m=(-3e-3, 15e-3),
        force_offset_n=OFFSET_N,
    )
    model = ForcepsModel(
        tissue=DEFAULT_TISSUE, operator=operator, sensors=sensors, seed=7, rate_hz=1000 / 3.003
    )
    session, _ = synthesize(model, 21.0)
    session = loggers.host_stamps(session, rng, quantum_s=1e-3, jitter_s=3e-4)
    session = loggers.pause(session, 9.1, 0.5)
    session = loggers.lose_at_random(session, 0.02, rng)
    gap = THICKNESS_M - session.position  # tip-to-tip distance, m
    angle_deg = np.degrees(2 * np.arcsin(gap / (2 * JAW_LENGTH_M)))
    force_g = session.force / 9.80665e-3
    millis = np.rint(session.time * 1e3).astype(np.int64) + 183_402  # since the board's reset
    lines = ["# logger v2.1 (simulated): millis, force in grams, jaw angle in degrees", ""]
    lines.append("millis\tforce_g\tangle_deg\tstatus")
    lines += [
        f"{m}\t{f:.1f}\t{a:.3f}\t{'OK' if k % 500 else 'SYNC'}"
        for k, (m, f, a) in enumerate(zip(millis, force_g, angle_deg, strict=True))
    ]
    lines.append(f"{millis[-1] + 3}\t12")  # the logger was unplugged mid-line
    path.write_bytes(("\r\n".join(lines)).encode())


def stage_heavy(path: Path) -> None:
    stage = Tissue(Law.paper("x", "xdot"), 20000.0, 1000.0, 100.0)
    sensors = Sensors(
        bits=16, force_noise_n=0.05, force_range_n=(-250.0, 250.0), position_range_m=(-1e-3, 20e-3)
    )
    operator = Operator.random(np.random.default_rng(11))
    model = ForcepsModel(tissue=stage, operator=operator, sensors=sensors, seed=11, rate_hz=500.0)
    s, _ = synthesize(model, 10.0)
    rows = [
        f"{t:.4f};{f:.3f};{x * 1e3:.5f}"
        for t, f, x in zip(s.time, s.force, s.position, strict=True)
    ]
    text = "\ufefftime (s);load (N);displacement (mm)\n" + "\n".join(rows) + "\n"
    path.write_text(text, encoding="utf-8")


if __name__ == "__main__":
    logger_grasps(HERE / "sim_logger_grasps.tsv")
    stage_heavy(HERE / "sim_stage_heavy.csv")
