"""Render a hyper.grow / hyper.cohort XDMF output with ParaView (pvbatch).

    xvfb-run -a pvbatch jobs/paraview_render.py results/cohort/runs/BFLH_VHF_Left_mwf_fields.xdmf \
        results/cohort/BFLH_VHF_Left_mwf_paraview.png [--scale 10] [--color detGbar]

Reads the last snapshot with Xdmf3ReaderT (the legacy XDMF reader crashes on XDMF 3):
one grid per snapshot time with every field (hyper.core.io.one_grid), warps it by u times
--scale and colours it by a cell or point array: by default (auto) the growth det Ḡ
where it varies over the mesh (heterogeneous signaling), else the displacement
magnitude |u| (uniform growth has one det Ḡ everywhere); --color detGbar or u to choose.
The reference shape stands in grey beside it. The longest side of the bounding box is
drawn upright and the camera looks along the shortest.
Prints the arrays and times found and checks that u and the colour array are there,
so a broken file fails loudly. Runs with ParaView's own Python (Debian: paraview,
python3-paraview), not the project's venv.
"""

import argparse
import os
import sys

from paraview.simple import (
    ColorBy,
    ExtractSurface,
    GetActiveViewOrCreate,
    GetColorTransferFunction,
    GetScalarBar,
    Render,
    SaveScreenshot,
    Show,
    Text,
    WarpByVector,
    Xdmf3ReaderT,
)

# det Ḡ counts as varying over the mesh when its range exceeds this fraction of its value
VARIES = 1e-6


def main(argv):
    p = argparse.ArgumentParser(prog="pvbatch jobs/paraview_render.py", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("xdmf", help="a *_fields.xdmf file of hyper.grow or hyper.cohort")
    p.add_argument("png", help="the picture to write")
    p.add_argument("--scale", type=float, default=10.0, help="displacement amplification (default 10)")
    p.add_argument("--color", default="auto",
                   help="array to colour by: auto (default: detGbar where it varies, else u), detGbar, u, …")
    args = p.parse_args(argv)

    # The reader finds the .h5 relative to the .xdmf only when given an absolute path.
    path = os.path.abspath(args.xdmf)
    if not os.path.isfile(path):
        sys.exit(f"error: {path}: no such file")
    reader = Xdmf3ReaderT(FileName=[path])
    times = list(reader.TimestepValues)
    if not times:
        sys.exit(f"error: {path}: no time steps")
    reader.UpdatePipeline(times[-1])
    point, cell = list(reader.PointData.keys()), list(reader.CellData.keys())
    print(f"{path}: {len(times)} snapshots, t = {times[0]:g} … {times[-1]:g} h; point data {point}, cell data {cell}")
    if "u" not in point:
        sys.exit(f"error: {path}: no point array u")
    if args.color == "auto":
        lo, hi = reader.CellData["detGbar"].GetRange() if "detGbar" in cell else (0.0, 0.0)
        args.color = "detGbar" if hi - lo > VARIES * abs(hi) else "u"
        print(f"colour: {args.color} (det Ḡ {lo:.6g} … {hi:.6g} over the mesh)")
    if args.color not in point + cell:
        sys.exit(f"error: {path}: no array {args.color!r}")
    association = "POINTS" if args.color in point else "CELLS"
    rng = (reader.PointData if association == "POINTS" else reader.CellData)[args.color].GetRange(-1)
    # the colours span what the picture shows, the surface: under uniform growth |u| varies
    # far less over it than through the interior (zero on the axis)
    surface = ExtractSurface(Input=reader)
    surface.UpdatePipeline(times[-1])
    shown_range = (surface.PointData if association == "POINTS" else surface.CellData)[args.color].GetRange(-1)
    print(f"{args.color}: range {rng[0]:.6g} … {rng[1]:.6g} at t = {times[-1]:g} h, on the surface "
          f"{shown_range[0]:.6g} … {shown_range[1]:.6g}")

    view = GetActiveViewOrCreate("RenderView")
    view.ViewTime = times[-1]
    view.ViewSize = [1000, 1000]
    view.Background = [1.0, 1.0, 1.0]
    view.OrientationAxesVisibility = 0
    try:  # ParaView ≥ 5.10 takes the background from the colour palette unless told not to
        view.UseColorPaletteForBackground = 0
    except AttributeError:
        pass

    warp = WarpByVector(Input=reader, Vectors=["POINTS", "u"], ScaleFactor=args.scale)
    warp.UpdatePipeline(times[-1])
    # The longest side of the bounding box upright; the camera looks along the shortest,
    # and the reference shape stands in grey beside the grown one, across the middle side.
    bounds = warp.GetDataInformation().GetBounds()
    size = [bounds[2 * i + 1] - bounds[2 * i] for i in range(3)]
    centre = [(bounds[2 * i + 1] + bounds[2 * i]) / 2 for i in range(3)]
    shortest, middle, longest = sorted(range(3), key=lambda i: size[i])
    shift = [0.0, 0.0, 0.0]
    shift[middle] = -1.3 * size[middle]
    reference = Show(reader, view)
    reference.Position = shift  # a display offset: the data stay where they are
    reference.ColorArrayName = ["POINTS", ""]  # solid grey
    reference.AmbientColor = reference.DiffuseColor = [0.7, 0.7, 0.7]

    shown = Show(warp, view)
    ColorBy(shown, (association, args.color, "Magnitude") if args.color == "u" else (association, args.color))
    lut = GetColorTransferFunction(args.color)
    lut.ApplyPreset("Viridis (matplotlib)", True)
    lo, hi = shown_range
    if hi - lo < 1e-9 * abs(hi):  # uniform growth: widen the range so the bar shows the value
        lo, hi = lo - 1e-4, hi + 1e-4
    lut.RescaleTransferFunction(lo, hi)
    shown.SetScalarBarVisibility(view, True)
    bar = GetScalarBar(lut, view)
    bar.Title = "u magnitude (m)" if args.color == "u" else args.color
    bar.ComponentTitle = ""
    bar.TitleColor = bar.LabelColor = [0.0, 0.0, 0.0]
    bar.RangeLabelFormat = "%-#.6g"
    bar.WindowLocation = "Any Location"
    bar.Position = [0.85, 0.1]
    text = Text(Text=f"{os.path.basename(path)}, t = {times[-1]:g} h\n"
                     f"grey: reference; colour: grown, u x{args.scale:g}")
    label = Show(text, view)
    label.Color = [0.0, 0.0, 0.0]
    label.FontSize = 14
    label.WindowLocation = "Upper Left Corner"

    focus = list(centre)
    focus[middle] += shift[middle] / 2
    position = list(focus)
    position[shortest] += 3.0 * size[longest]
    up = [0.0, 0.0, 0.0]
    up[longest] = 1.0
    view.CameraPosition = position
    view.CameraFocalPoint = focus
    view.CameraViewUp = up
    view.CameraParallelProjection = 1
    view.CameraParallelScale = 0.6 * size[longest]
    Render(view)
    SaveScreenshot(os.path.abspath(args.png), view, ImageResolution=[1000, 1000])
    print(f"wrote {os.path.abspath(args.png)}")


if __name__ == "__main__":
    main(sys.argv[1:])
