"""Run by ``pvbatch`` (ParaView's Python, not massview's) for ``massview bench paraview``.

    pvbatch pvbatch_script.py HEIGHTS.raw ROWS COLS DX DY VSCALE STEP CAMERAS.json OUT.json [LAST.png]

Reads a float32 row-major height grid (rows flipped so +y is north, as massview draws it: x =
col·dx, y = -row·dy, z = h·vscale), keeps every STEP-th sample (STEP 2 ≈ a quarter of the
triangles), turns it into a warped surface and renders the cameras at their image size with
the default ParaView render view (IceT compositing under MPI). Timed per camera, after one
untimed render that runs the pipeline: ``Render()`` plus reading the composited image back on
rank 0. Rank 0 writes per-frame seconds, triangles and the ranks to OUT.json.
"""

import json
import sys
import time

from paraview import servermanager as sm
from paraview.vtk import vtkUnsignedCharArray
from paraview.simple import (CreateRenderView, ExtractSubset, ExtractSurface, GetActiveViewOrCreate, ImageReader, Render,  # noqa: F401
                             Show, Triangulate, WarpByScalar)

raw, rows, cols, dx, dy, vscale, step, cams_path, out_path = sys.argv[1:10]
rows, cols, step = int(rows), int(cols), int(step)
dx, dy, vscale = float(dx), float(dy), float(vscale)
reader = ImageReader(FileNames=[raw])
reader.DataScalarType = "float"
reader.DataByteOrder = "LittleEndian"
reader.DataExtent = [0, cols - 1, 0, rows - 1, 0, 0]
reader.DataSpacing = [dx, dy, 1.0]
reader.DataOrigin = [0.0, -(rows - 1) * dy, 0.0]
src = ExtractSubset(Input=reader, VOI=[0, cols - 1, 0, rows - 1, 0, 0], SampleRateI=step, SampleRateJ=step) if step > 1 else reader
surf = Triangulate(Input=ExtractSurface(Input=src))
warp = WarpByScalar(Input=surf, Scalars=["POINTS", "ImageFile"], ScaleFactor=vscale, Normal=[0.0, 0.0, 1.0], UseNormal=1)
cams = json.load(open(cams_path))
view = GetActiveViewOrCreate("RenderView")
view.ViewSize = cams["size"]
view.OrientationAxesVisibility = 0
disp = Show(warp, view)
disp.Representation = "Surface"


def look(c):
    view.CameraPosition, view.CameraFocalPoint, view.CameraViewUp = c["position"], c["focal"], c["up"]
    view.CameraViewAngle = c["fovy"]
    view.CameraParallelProjection = 0


pm = sm.vtkProcessModule.GetProcessModule()
root = pm.GetPartitionId() == 0
pixels = vtkUnsignedCharArray()


def frame():
    """Render (each rank draws its piece, IceT composites) and read the image back on rank 0."""
    Render(view)
    if root:
        w, h = cams["size"]
        view.GetRenderWindow().GetRGBACharPixelData(0, 0, w - 1, h - 1, 0, pixels)


look(cams["cameras"][0])
frame()  # runs the pipeline (read, subset, surface, warp) once, untimed
times = []
for c in cams["cameras"]:
    look(c)
    t0 = time.perf_counter()
    frame()
    times.append(time.perf_counter() - t0)
if len(sys.argv) > 10:  # a picture of the last camera, to check the view matches massview's
    from paraview.simple import SaveScreenshot

    SaveScreenshot(sys.argv[10], view, ImageResolution=cams["size"])
if root:
    ncell = warp.GetDataInformation().GetNumberOfCells()
    json.dump({"seconds": times, "triangles": ncell, "ranks": pm.GetNumberOfLocalPartitions()}, open(out_path, "w"))
