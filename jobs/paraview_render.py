"""Render a hyper.grow / hyper.cohort XDMF output with ParaView (pvbatch).

    xvfb-run -a pvbatch jobs/paraview_render.py results/cohort/runs/BFLH_VHF_Left_mwf_fields.xdmf \
        results/cohort/BFLH_VHF_Left_mwf_paraview.png [--scale 10] [--color detGbar]

Reads the last snapshot with Xdmf3ReaderT (DOLFINx writes XDMF 3; the legacy XDMF
reader crashes on it), merges the per-function blocks that DOLFINx writes into one
grid, warps it by u times --scale and colours it by a cell or point array (default
detGbar, the growth det Ḡ; --color u for the displacement magnitude), with the
reference shape in grey beside it. The longest side of the bounding box is drawn
upright and the camera looks along the shortest.
Prints the arrays and times found and checks that u and the colour array are there,
so a broken file fails loudly. Runs with ParaView's own Python (Debian: paraview,
python3-paraview), not the project's venv.
"""

import argparse
import builtins
import os
import sys

from paraview.simple import (
    ColorBy, GetActiveViewOrCreate, GetColorTransferFunction, GetScalarBar, ProgrammableFilter, Render,
    SaveScreenshot, Show, Text, WarpByVector, Xdmf3ReaderT,
)


MERGE_BLOCKS = """
blocks = self.GetInputDataObject(0, 0)
out = self.GetOutputDataObject(0)
out.ShallowCopy(blocks.GetBlock(0))
for i in range(1, blocks.GetNumberOfBlocks()):
    block = blocks.GetBlock(i)
    for data, into in ((block.GetPointData(), out.GetPointData()), (block.GetCellData(), out.GetCellData())):
        for k in range(data.GetNumberOfArrays()):
            into.AddArray(data.GetArray(k))
"""


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
    # DOLFINx writes each function as its own grid on the same mesh: the reader gives one
    # block per function (u, detGbar, a0). Put all arrays on one grid for the filters.
    reader = ProgrammableFilter(Input=reader, OutputDataSetType="vtkUnstructuredGrid", Script=MERGE_BLOCKS)
    reader.UpdatePipeline(times[-1])
    # The filter ran its script in this module's namespace, whose max and abs are now
    # numpy_interface's: use builtins.max and builtins.abs from here on.
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
    lo, hi = rng
    if hi - lo < 1e-9 * builtins.abs(hi):  # uniform growth: widen the range so the bar shows the value
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
