"""Render a hyper.grow / hyper.cohort XDMF output with ParaView (pvbatch).

    xvfb-run -a pvbatch jobs/paraview_render.py results/cohort/runs/BFLH_VHF_Left_mwf_fields.xdmf \
        results/cohort/BFLH_VHF_Left_mwf_paraview.png [--scale 10] [--color detGbar]

Reads the last snapshot with Xdmf3ReaderT (DOLFINx writes XDMF 3; the legacy XDMF
reader crashes on it), warps the mesh by u times --scale, colours it by a cell or point
array (default detGbar, the growth det Ḡ) and draws the reference shape as a grey
wireframe. The camera looks across the muscle's longest side, which is drawn upright.
Prints the arrays and times found and checks that u and the colour array are there,
so a broken file fails loudly. Runs with ParaView's own Python (Debian: paraview,
python3-paraview), not the project's venv.
"""

import argparse
import os
import sys

from paraview.simple import (
    ColorBy, GetActiveViewOrCreate, GetColorTransferFunction, Render, SaveScreenshot, Show,
    WarpByVector, Xdmf3ReaderT,
)


def main(argv):
    p = argparse.ArgumentParser(prog="pvbatch jobs/paraview_render.py", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("xdmf", help="a *_fields.xdmf file of hyper.grow or hyper.cohort")
    p.add_argument("png", help="the picture to write")
    p.add_argument("--scale", type=float, default=10.0, help="displacement amplification (default 10)")
    p.add_argument("--color", default="detGbar", help="array to colour by (default detGbar; or u)")
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
    if args.color not in point + cell:
        sys.exit(f"error: {path}: no array {args.color!r}")
    association = "POINTS" if args.color in point else "CELLS"
    rng = (reader.PointData if association == "POINTS" else reader.CellData)[args.color].GetRange(-1)
    print(f"{args.color}: range {rng[0]:.6g} … {rng[1]:.6g} at t = {times[-1]:g} h")

    view = GetActiveViewOrCreate("RenderView")
    view.ViewTime = times[-1]
    view.ViewSize = [700, 1000]
    view.Background = [1.0, 1.0, 1.0]
    view.OrientationAxesVisibility = 0
    try:  # ParaView ≥ 5.10 takes the background from the colour palette unless told not to
        view.UseColorPaletteForBackground = 0
    except AttributeError:
        pass

    reference = Show(reader, view)
    reference.Representation = "Wireframe"
    reference.AmbientColor = reference.DiffuseColor = [0.6, 0.6, 0.6]
    reference.Opacity = 0.15
    ColorBy(reference, None)

    warp = WarpByVector(Input=reader, Vectors=["POINTS", "u"], ScaleFactor=args.scale)
    shown = Show(warp, view)
    ColorBy(shown, (association, args.color, "Magnitude") if args.color == "u" else (association, args.color))
    lut = GetColorTransferFunction(args.color)
    lut.ApplyPreset("Viridis (matplotlib)", True)
    lo, hi = rng
    if hi - lo < 1e-9 * max(1.0, abs(hi)):  # uniform growth: widen the range so the bar shows the value
        lo, hi = lo - 1e-4, hi + 1e-4
    lut.RescaleTransferFunction(lo, hi)
    shown.SetScalarBarVisibility(view, True)
    bar = lut.GetScalarBar(view) if hasattr(lut, "GetScalarBar") else None
    if bar is not None:
        bar.Title = f"{args.color} (u ×{args.scale:g})"
        bar.ComponentTitle = ""
        bar.TitleColor = bar.LabelColor = [0.0, 0.0, 0.0]
        bar.RangeLabelFormat = "%-#.4f"

    # Camera: the longest side of the bounding box upright, looking along the shortest.
    bounds = warp.GetDataInformation().GetBounds()
    size = [bounds[2 * i + 1] - bounds[2 * i] for i in range(3)]
    centre = [(bounds[2 * i + 1] + bounds[2 * i]) / 2 for i in range(3)]
    order = sorted(range(3), key=lambda i: size[i])
    shortest, longest = order[0], order[2]
    distance = 2.2 * max(size)
    position = list(centre)
    position[shortest] += distance
    up = [0.0, 0.0, 0.0]
    up[longest] = 1.0
    view.CameraPosition = position
    view.CameraFocalPoint = centre
    view.CameraViewUp = up
    view.CameraParallelProjection = 1
    view.CameraParallelScale = 0.55 * size[longest]
    Render(view)
    SaveScreenshot(os.path.abspath(args.png), view, ImageResolution=[700, 1000])
    print(f"wrote {os.path.abspath(args.png)}")


if __name__ == "__main__":
    main(sys.argv[1:])
