"""A still of a run.mcap at one time, drawn with matplotlib from the file's own /tf and /scene messages: a
STAND-IN for a Foxglove 3D-panel screenshot (no Foxglove involved), for docs and quick looks.

    python tools/mcap_snapshot.py RUN_DIR/run.mcap --t 12 --out snapshot.png

Reads with the `mcap` reader and `mcap-protobuf-support` (the test extras). Draws every unit's box (colour:
health) and rotor discs (colour: eta, size: thrust) where /tf puts them, the planned path and the reference
flown so far, in the ENU map frame (east, north, up), with the /events logged up to that time.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def _q(r) -> np.ndarray:
    return np.array([r.w, r.x, r.y, r.z])


def _rot(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def snapshot(mcap_path: Path, t_s: float, out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    want = int(t_s * 1e9)
    dec = DecoderFactory()
    tf = scene = None
    events = []
    with open(mcap_path, "rb") as f:
        for schema, ch, msg in make_reader(f).iter_messages(topics=["/tf", "/scene", "/events"], ending_at=want):
            m = dec.decoder_for(ch.message_encoding, schema)(msg.data)
            if ch.topic == "/tf":
                tf = m
            elif ch.topic == "/scene":
                scene = m
            else:
                events.append((msg.log_time / 1e9, m.message))
    if tf is None or scene is None:
        raise SystemExit(f"{mcap_path}: no /tf and /scene before t = {t_s:g} s")
    frames = {t.child_frame_id: t for t in tf.transforms}
    enu = _rot(_q(frames["world"].rotation))  # NED -> ENU (map)

    def world_pose(frame: str):
        t = frames[frame]
        p, r = np.array([t.translation.x, t.translation.y, t.translation.z]), _rot(_q(t.rotation))
        if t.parent_frame_id in ("world", "map"):
            return p, r
        pp, pr = world_pose(t.parent_frame_id)
        return pp + pr @ p, pr @ r

    fig = plt.figure(figsize=(7.5, 5.0), dpi=90)
    ax = fig.add_subplot(projection="3d")
    for ent in scene.entities:
        if ent.frame_id == "world":
            for line in ent.lines:
                pts = np.array([[p.x, p.y, p.z] for p in line.points]) @ enu.T
                c = (line.color.r, line.color.g, line.color.b)
                ax.plot(pts[:, 0], pts[:, 1], pts[:, 2], color=c, lw=1.5 if ent.id == "reference" else 0.8,
                        label=ent.id)
            continue
        p, r = world_pose(ent.frame_id)
        for cube in ent.cubes:
            h = cube.size.x / 2
            corners = np.array([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0], [-h, -h, 0]])
            pts = (p + corners @ r.T) @ enu.T
            c = (cube.color.r, cube.color.g, cube.color.b)
            ax.plot(pts[:, 0], pts[:, 1], pts[:, 2], color=c, lw=2)
        for cyl in ent.cylinders:
            centre = (p + r @ np.array([cyl.pose.position.x, cyl.pose.position.y, cyl.pose.position.z])) @ enu.T
            ax.scatter(*centre, s=400 * cyl.size.x, color=(cyl.color.r, cyl.color.g, cyl.color.b), alpha=0.8)
    ax.set(xlabel="east [m]", ylabel="north [m]", zlabel="up [m]")
    ax.set_title(f"run.mcap at t = {t_s:g} s (matplotlib stand-in, not Foxglove)", fontsize=9)
    if events:
        fig.text(0.02, 0.02, "\n".join(f"{t:6.2f} s  {m}" for t, m in events[-4:]), fontsize=7, family="monospace")
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mcap")
    ap.add_argument("--t", type=float, default=10.0, help="simulated time [s]")
    ap.add_argument("--out", default="snapshot.png")
    a = ap.parse_args()
    print(f"wrote {snapshot(Path(a.mcap), a.t, Path(a.out))}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
