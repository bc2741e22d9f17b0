"""Run by ``pvbatch`` (ParaView's Python, not massview's) for ``massview bench paraview``.

    pvbatch pvbatch_script.py HEIGHTS.raw ROWS COLS DX DY VSCALE STEP CAMERAS.json OUT.json [LAST.png]

Reads a float32 row-major height grid (rows flipped so +y is north, as massview draws it: x =
col·dx, y = -row·dy, z = h·vscale), keeps every STEP-th sample (STEP 2 ≈ a quarter of the
triangles), turns it into a warped surface and renders the cameras at their image size with
the default ParaView render view (IceT compositing under MPI). Timed per camera, after one
untimed render that runs the pipeline: ``Render()`` plus reading the composited image back on
rank 0. Rank 0 writes per-frame seconds, triangles and the ranks to OUT.json.

IceT's own timers, per frame and rank: after each ``Render()`` the IceT context ParaView's
``vtkIceTCompositePass`` drew with is still current, and IceT's state holds that frame's
timings (IceT 2.1 ``IceT.h``: ``ICET_RENDER_TIME`` … ``ICET_BYTES_SENT``, 0xC1–0xCA), read
with ``icetGetDoublev`` from the ``libvtkIceTCore`` ParaView already loaded (ctypes). Every
rank writes them to OUT.json.icet.RANK.json (none when the library is not found or no IceT
context is current, e.g. one rank without compositing).
"""

import ctypes
import glob
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
ICET_TIMERS = {"render": 0xC1, "buffer_read": 0xC2, "buffer_write": 0xC3, "compress": 0xC4, "interlace": 0xC5,
               "blend": 0xC6, "composite": 0xC7, "collect": 0xC8, "total_draw": 0xC9}
ICET_BYTES_SENT = 0xCA


def icet_library():
    """ParaView's IceT core library (already loaded by the render view), or None."""
    for path in sorted(glob.glob("/usr/lib*/**/libvtkIceTCore*.so*", recursive=True)) + ["libvtkIceTCore-pv5.11.so"]:
        try:
            lib = ctypes.CDLL(path)
            lib.icetGetContext.restype = ctypes.c_void_p
            return lib
        except OSError:
            continue
    return None


icet = icet_library()


def icet_timings():
    """This rank's IceT timers of the frame just drawn (seconds; bytes sent), or None."""
    if icet is None or not icet.icetGetContext():
        return None
    out, d, n = {}, ctypes.c_double(), ctypes.c_int()
    for name, enum in ICET_TIMERS.items():
        icet.icetGetDoublev(ctypes.c_uint(enum), ctypes.byref(d))
        out[name] = d.value
    icet.icetGetIntegerv(ctypes.c_uint(ICET_BYTES_SENT), ctypes.byref(n))
    out["bytes_sent"] = n.value
    return out


def frame():
    """Render (each rank draws its piece, IceT composites) and read the image back on rank 0."""
    Render(view)
    if root:
        w, h = cams["size"]
        view.GetRenderWindow().GetRGBACharPixelData(0, 0, w - 1, h - 1, 0, pixels)


look(cams["cameras"][0])
frame()  # runs the pipeline (read, subset, surface, warp) once, untimed
times, icet_frames = [], []
for c in cams["cameras"]:
    look(c)
    t0 = time.perf_counter()
    frame()
    times.append(time.perf_counter() - t0)
    icet_frames.append(icet_timings())
if all(f is not None for f in icet_frames):
    json.dump({"rank": pm.GetPartitionId(), "frames": icet_frames}, open(f"{out_path}.icet.{pm.GetPartitionId()}.json", "w"))
if len(sys.argv) > 10:  # a picture of the last camera, to check the view matches massview's
    from paraview.simple import SaveScreenshot

    SaveScreenshot(sys.argv[10], view, ImageResolution=cams["size"])
if root:
    ncell = warp.GetDataInformation().GetNumberOfCells()
    json.dump({"seconds": times, "triangles": ncell, "ranks": pm.GetNumberOfLocalPartitions()}, open(out_path, "w"))
