"""Regenerate the README's seed-000 figures: python docs/make_figures.py (about 4 minutes on 2 cores).

Runs seed000 over CAN and in the ideal loop, and the consensus baseline over CAN, for 800 s each.
"""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from hil.runtime.ideal import IdealLoop  # noqa: E402
from hil.runtime.virtual import VirtualRig  # noqa: E402
from hil.scenario import load_scenario  # noqa: E402

OUT = Path(__file__).parent / "figures"


def panel(axes, log, title: str) -> None:
    kmh = 3.6
    axes[0].plot(log.t, log.v * kmh, lw=0.8)
    axes[0].plot(log.t, log.v_ref * kmh, "k--", lw=1.0, label="v_r")
    axes[0].set(title=title, ylabel="speed (km/h)")
    axes[0].legend(loc="upper right")
    axes[1].plot(log.t, log.couplers, lw=0.6)
    for y in (-0.1, 0.1):
        axes[1].axhline(y, color="r", ls=":", lw=1)
    axes[1].set(ylabel="coupler e (m)", ylim=(-0.2, 0.2))
    axes[2].plot(log.t, log.gaps, lw=1.0)
    axes[2].axhline(3000, color="k", ls="--", lw=1, label="l_s")
    axes[2].axhline(1500, color="r", ls=":", lw=1, label="l_e")
    axes[2].set(ylabel="gap (m)", xlabel="t (s)")
    axes[2].legend(loc="upper right")


def main() -> None:
    OUT.mkdir(exist_ok=True)
    runs = [
        ("finite-time law over CAN (seed000)", VirtualRig(load_scenario("seed000")).run()),
        ("finite-time law, ideal loop (no network)", IdealLoop(load_scenario("seed000")).run()),
        ("ordinary consensus over CAN (seed000-consensus)", VirtualRig(load_scenario("seed000-consensus")).run()),
    ]
    fig, axes = plt.subplots(3, len(runs), figsize=(6 * len(runs), 9), sharex=True)
    for k, (title, log) in enumerate(runs):
        panel(axes[:, k], log, title)
    fig.tight_layout()
    fig.savefig(OUT / "seed000.png", dpi=90)
    print(f"wrote {OUT / 'seed000.png'}")


if __name__ == "__main__":
    main()
