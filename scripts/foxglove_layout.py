"""``dtpf layout``: a Foxglove layout for a twin, built with foxglove-sdk's layout API.

Five panels: the estimate against the truth with its 95% band (Plot), the
latest forecast's mean and 95% band over the steps ahead (Plot; an entity run
with ``--forecast H``), ESS/N and PS with the degraded steps (Plot), the
particle cloud coloured by weight (3D), and the video frame with the particles
drawn over it (Image; the video scenario only). In Foxglove: Layouts, Import
from file::

    dtpf layout --twin ungm-1 -o docs/foxglove-layout.json
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["layout_json", "register"]


def layout_json(twin: str) -> str:
    """The layout's JSON (Foxglove's format, as foxglove-sdk writes it)."""
    from foxglove import layouts as fl

    # A topic that does not start with a slash is quoted in a Foxglove message path.
    estimate_topic = f'"dtpf/{twin}/entity/estimate"'

    def series(path: str, label: str, **style) -> fl.PlotSeries:
        return fl.PlotSeries(value=path, label=label, enabled=True, timestamp_method="receiveTime", **style)

    estimate = fl.PlotPanel(title="estimate, truth and 95% band", config=fl.PlotConfig(paths=[
        series(f"{estimate_topic}.mean[0]", "estimate", color="#d62728"),
        series(f"{estimate_topic}.truth[0]", "truth", color="#1f77b4"),
        series(f"{estimate_topic}.lower[0]", "lower 95%", color="#ff9896", line_style="dashed"),
        series(f"{estimate_topic}.upper[0]", "upper 95%", color="#ff9896", line_style="dashed"),
    ], show_legend=True))
    band_topic = f'"dtpf/{twin}/entity/forecast_band"'
    ahead = fl.PlotPanel(title="forecast ahead of the latest step, 95% band", config=fl.PlotConfig(
        paths=[series(f"{band_topic}.ahead[:].mean[0]", "forecast", color="#d62728"),
               series(f"{band_topic}.ahead[:].lower[0]", "lower 95%", color="#ff9896", line_style="dashed"),
               series(f"{band_topic}.ahead[:].upper[0]", "upper 95%", color="#ff9896", line_style="dashed")],
        x_axis_val="currentCustom", x_axis_path=fl.PlotXAxisPath(value=f"{band_topic}.ahead[:].step", enabled=True),
        x_axis_label="step", show_legend=True))
    health = fl.PlotPanel(title="ESS/N, PS, degraded", config=fl.PlotConfig(paths=[
        series(f"{estimate_topic}.ess_ratio", "ESS/N", color="#2ca02c"),
        series(f"{estimate_topic}.ps", "PS applied", color="#9467bd"),
        series(f"{estimate_topic}.degraded", "degraded", color="#7f7f7f", line_interpolation="step"),
    ], show_legend=True, min_y_value=0.0, max_y_value=1.0))
    cloud = fl.ThreeDeePanel(title="particle cloud", config=fl.ThreeDeeConfig(
        follow_tf="state", topics={f"dtpf/{twin}/entity/cloud": fl.BaseRendererPointCloudTopicSettings(
            visible=True, point_size=4.0, color_mode="colormap", color_field="weight", color_map="turbo")}))
    frame = fl.ImagePanel(title="frame and particles (video scenario)", config=fl.ImageConfig(
        image_mode=fl.ImageModeConfig(image_topic=f"dtpf/{twin}/entity/frame",
                                      annotations={f"dtpf/{twin}/entity/annotations": fl.ImageAnnotationSettings(visible=True)})))
    content = fl.SplitContainer(direction="column", items=[
        fl.SplitItem(proportion=1, content=fl.SplitContainer(direction="row", items=[
            fl.SplitItem(proportion=2, content=estimate), fl.SplitItem(proportion=1, content=ahead),
            fl.SplitItem(proportion=1, content=health)])),
        fl.SplitItem(proportion=1, content=fl.SplitContainer(direction="row", items=[
            fl.SplitItem(proportion=1, content=cloud), fl.SplitItem(proportion=1, content=frame)])),
    ])
    return fl.Layout(content=content).to_json()


def cmd_layout(args: argparse.Namespace) -> int:
    try:
        text = layout_json(args.twin)
    except ImportError:
        print("dtpf layout: error: the layout is built with foxglove-sdk: pip install 'dtpf[foxglove]'", file=sys.stderr)
        return 2
    if args.output is None:
        print(text)
    else:
        Path(args.output).write_text(text + "\n")
        print(f"wrote {args.output} (Foxglove: Layouts, Import from file)", file=sys.stderr)
    return 0


def register(subparsers) -> None:
    """Add the ``layout`` command to an argparse subparsers object."""
    parser = subparsers.add_parser(
        "layout", help="write a Foxglove layout for a twin: estimate and band, forecast, ESS/N and PS, cloud, frame",
        description=__doc__.split("\n\n")[1].replace("\n", " "))
    parser.add_argument("--twin", default="ungm-1", help="twin the layout shows (default: %(default)s)")
    parser.add_argument("--output", "-o", type=Path, default=None, metavar="FILE",
                        help="file to write (default: standard output)")
    parser.set_defaults(handler=cmd_layout)
