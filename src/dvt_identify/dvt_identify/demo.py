"""The README's demo (``scripts/demo.sh OUTDIR``).

Stage 1 (model): a run simulated by the physics core is written as a bag, replayed with
``dvt-replay`` into the live ``dvt_model_node``, and the model's prediction is recorded from the
topics and plotted against the measurement (``OUTDIR/model_replay.png``).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

BIN = Path(sys.executable).parent


def _log(msg: str) -> None:
    print(f"[demo] {msg}", flush=True)


def simulated_bag(path: Path, seconds: float = 6.0, seed: int = 7) -> Path:
    """A run simulated by the physics core (plant parameters, sensor noise) as a bag."""
    from dvt_model.bagio import write_run
    from dvt_model.hybrid import HybridModel
    from dvt_model.params import load_parameters

    model = HybridModel.from_params(load_parameters("physical"))
    n = int(seconds * 1000)
    t = np.arange(n) * 1e-3
    im = 5.0 + 3.0 * np.sign(np.sin(2 * np.pi * 0.5 * t))
    ib = np.zeros((n, 3))
    ib[(t >= 2.0) & (t < 4.0), 0] = 0.5
    ib[t >= 4.0, 1] = 0.6
    r = model.simulate(t, im, ib, omega0=(0.0, 0.0))
    rng = np.random.default_rng(seed)
    speeds = r.omega + rng.normal(0.0, 0.3, r.omega.shape)
    stamps = (time.time_ns() // 10**9 * 10**9 + np.round(t * 1e9)).astype(np.int64)
    return write_run(path, stamps, speeds, np.column_stack([im, ib]))


def model_replay(out: Path) -> dict[str, Any]:
    """Stage 1: replay a simulated bag into the model node and plot measured vs predicted."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState

    from dvt_model import rosutil
    from dvt_model.bagio import read_run

    bag = simulated_bag(out / "simulated_run")
    _log(f"simulated run written to {bag}")
    node = subprocess.Popen([str(BIN / "dvt_model_node")], start_new_session=True)
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(os.environ.get("ROS_DOMAIN_ID", "0")))
    listener = rclpy.create_node("dvt_demo_listener", context=ctx)
    exe = SingleThreadedExecutor(context=ctx)
    exe.add_node(listener)
    pred: dict[int, list[float]] = {}
    def on_pred(m: JointState) -> None:
        pred[rosutil.stamp_to_ns(m.header.stamp)] = list(m.velocity)

    listener.create_subscription(JointState, rosutil.MODEL_JOINT_STATES, on_pred,
                                 rosutil.SENSOR_QOS)
    try:
        deadline = time.monotonic() + 30
        while listener.count_publishers(rosutil.MODEL_JOINT_STATES) < 1:
            exe.spin_once(timeout_sec=0.05)
            if time.monotonic() > deadline:
                raise RuntimeError("model node did not start within 30 s")
        replay = subprocess.Popen([str(BIN / "dvt-replay"), str(bag), "--wait-subscribers", "1"])
        while replay.poll() is None:
            exe.spin_once(timeout_sec=0.05)
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            exe.spin_once(timeout_sec=0.05)
    finally:
        node.send_signal(signal.SIGINT)
        node.wait(timeout=10)
        listener.destroy_node()
        rclpy.shutdown(context=ctx)
    run = read_run(bag)
    idx = np.array([k for k, s in enumerate(run.stamps_ns) if int(s) in pred])
    yhat = np.array([pred[int(run.stamps_ns[k])] for k in idx])
    y = run.speeds[idx]
    t = run.t[idx]
    rms = np.sqrt(np.mean((y - yhat) ** 2, axis=0))
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    for ax, j, name in ((axes[0], 0, "sun shaft"), (axes[1], 1, "carrier 3")):
        ax.plot(t, y[:, j], lw=0.6, label="measured (simulated plant + noise)")
        ax.plot(t, yhat[:, j], lw=1.0, label="dvt_model_node prediction")
        ax.set_ylabel(f"{name} [rad/s]")
        ax.legend(loc="upper left", fontsize=8)
    axes[2].plot(t, run.currents[idx, 0], label="drive motor [A]")
    for k in range(3):
        axes[2].plot(t, 10 * run.currents[idx, 1 + k], label=f"brake {k + 1} [A x10]")
    axes[2].set_xlabel("time [s]")
    axes[2].legend(loc="upper left", fontsize=8)
    fig.suptitle(f"Model node on a replayed run: residual RMS sun {rms[0]:.3f}, "
                 f"carrier3 {rms[1]:.3f} rad/s")
    fig.tight_layout()
    png = out / "model_replay.png"
    fig.savefig(png, dpi=110)
    summary = {"samples": len(run.t), "predicted": len(idx),
               "residual_rms_rad_s": {"sun_shaft": float(rms[0]), "carrier3": float(rms[1])},
               "plot": str(png)}
    _log(f"model replay: {json.dumps(summary)}")
    return summary


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    out = Path(args[0] if args else "demo-out").resolve()
    out.mkdir(parents=True, exist_ok=True)
    summary = {"model_replay": model_replay(out)}
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    _log(f"done: {out / 'summary.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
