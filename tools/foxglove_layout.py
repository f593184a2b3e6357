"""Write the Foxglove layout for mars-link runs (tools/mars_link_foxglove_layout.json), built with the
Foxglove SDK's own layout classes (foxglove.layouts): a 3D panel on /scene following the ENU "map" frame with
the reference, truth and estimate poses, plots of the tracking error and of every rotor's thrust, the
/events log.

    python tools/foxglove_layout.py [--units 6] [--out tools/mars_link_foxglove_layout.json]

Import it in Foxglove: Layouts -> Import from file. --units: how many units' rotors the thrust plot lists
(the checked-in file: 6, the default 3x2).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import foxglove.layouts as fl

HERE = Path(__file__).resolve().parent


def layout(units: int = 6) -> fl.Layout:
    three_d = fl.ThreeDeePanel(title="assembly (map: ENU, z up)", config=fl.ThreeDeeConfig(
        follow_tf="map", follow_mode="follow-none",
        topics={
            "/scene": fl.BaseRendererSceneUpdateTopicSettings(visible=True),
            "/reference": fl.BaseRendererPoseTopicSettings(visible=True),
            "/truth": fl.BaseRendererPoseTopicSettings(visible=True),
            "/estimate": fl.BaseRendererPoseTopicSettings(visible=True),
        },
        layers={"grid": fl.BaseRendererGridLayerSettings(frame_id="map")},
    ))
    error = fl.PlotPanel(title="tracking error [m]", config=fl.PlotConfig(paths=[
        fl.PlotSeries(value="/error.error_m", label="|error|", enabled=True),
        fl.PlotSeries(value="/error.north_m", label="north", enabled=False),
        fl.PlotSeries(value="/error.east_m", label="east", enabled=False),
        fl.PlotSeries(value="/error.down_m", label="down", enabled=False),
    ]))
    thrust = fl.PlotPanel(title="rotor thrust [N] (unit u rotor r = 4(u-1)+r-1)", config=fl.PlotConfig(paths=[
        fl.PlotSeries(value=f"/rotors.thrust_n[{4 * (u - 1) + r - 1}]", label=f"u{u}r{r}", enabled=True)
        for u in range(1, units + 1) for r in range(1, 5)
    ]))
    log = fl.LogPanel(title="events", config=fl.LogConfig(topic_to_render="/events"))
    return fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=3, content=three_d),
        fl.SplitItem(proportion=2, content=fl.SplitContainer(direction="column", items=[
            fl.SplitItem(content=error), fl.SplitItem(content=thrust), fl.SplitItem(content=log)])),
    ]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--units", type=int, default=6)
    ap.add_argument("--out", default=str(HERE / "mars_link_foxglove_layout.json"))
    a = ap.parse_args()
    if not 1 <= a.units <= 1000:
        ap.error("--units must be 1..1000")
    Path(a.out).write_text(layout(a.units).to_json() + "\n", encoding="utf-8")
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
