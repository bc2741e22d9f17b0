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
with ``icetGetDoublev`` from the ``libvtkIceTCore`` ParaView already loaded (ctypes). pvbatch
runs this script on rank 0 only (the other ranks serve), so these are rank 0's timers — the
display rank, whose compositing time includes waiting for the other ranks' images. They go to
OUT.json.icet.0.json (a frame's entry is null when the library is not
found or no IceT context is current, e.g. one rank without compositing).
"""

import ctypes
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
    """ParaView's IceT core library, the copy this process already loaded (found in
    /proc/self/maps, else by its soname), or None."""
    paths = []
    try:
        with open("/proc/self/maps") as maps:
            paths = sorted({line.split()[-1] for line in maps if "libvtkIceTCore" in line})
    except OSError:
        pass
    for path in paths + ["libvtkIceTCore-pv5.11.so.1"]:
        try:
            lib = ctypes.CDLL(path)
            lib.icetGetContext.restype = ctypes.c_void_p
            return lib
        except (OSError, AttributeError):
            continue
    return None


icet = None  # looked up after the first render, when the render view has loaded it


def icet_timings():
    """This rank's IceT timers of the frame just drawn (seconds; bytes sent), or None."""
    global icet
    icet = icet or icet_library()
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
json.dump({"rank": pm.GetPartitionId(), "frames": icet_frames, "library": getattr(icet, "_name", None)},
          open(f"{out_path}.icet.{pm.GetPartitionId()}.json", "w"))
if len(sys.argv) > 10:  # a picture of the last camera, to check the view matches massview's
    from paraview.simple import SaveScreenshot

    SaveScreenshot(sys.argv[10], view, ImageResolution=cams["size"])
if root:
    ncell = warp.GetDataInformation().GetNumberOfCells()
    json.dump({"seconds": times, "triangles": ncell, "ranks": pm.GetNumberOfLocalPartitions()}, open(out_path, "w"))
