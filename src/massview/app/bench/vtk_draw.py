"""The peer's draw throughput: pyvista/VTK renders the same triangles offscreen (a child process).

``python -m massview.app.bench.vtk_draw MESH.npz CAMERAS.json REPS`` loads ``points`` (N, 3)
float32 world positions, ``normals`` (N, 3) float32, ``triangles`` (T, 3) int vertex indices,
builds one ``pyvista.PolyData`` (one VBO and one ``glDrawElements`` in VTK's
vtkOpenGLPolyDataMapper), and renders it offscreen (EGL: llvmpipe on this machine, like
massview) at each camera of CAMERAS.json (``Camera.to_json`` records: same position, view
direction, fovy, clip planes and image size as massview's), ``REPS`` times after one warm-up
render (which uploads the buffers). VTK settings: no multisampling (massview draws one sample
per pixel), default light kit, the given point normals (Gouraud-interpolated, like the plain
mesh). Prints one JSON line: ``{"renderer", "triangles", "wall_s", "cpu_s", "main_s"}`` (lists: wall,
process CPU and calling-thread CPU seconds, one entry per ``Render()`` + ``glFinish``).
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np


def main(argv: list[str]) -> int:
    import pyvista as pv

    from ...core.camera import Camera

    mesh_path, cams_path, reps = argv[0], argv[1], int(argv[2])
    d = np.load(mesh_path)
    tris = np.asarray(d["triangles"])
    poly = pv.PolyData.from_regular_faces(np.asarray(d["points"], np.float32), tris)
    poly.point_data["Normals"] = np.asarray(d["normals"], np.float32)
    poly.point_data.active_normals_name = "Normals"
    del d
    cams = [Camera.from_json(c) for c in json.loads(open(cams_path).read())]
    pl = pv.Plotter(off_screen=True, window_size=(cams[0].width, cams[0].height))
    pl.ren_win.SetMultiSamples(0)
    pl.add_mesh(poly, color=(0.7, 0.67, 0.6), smooth_shading=True)
    rw, vc = pl.ren_win, pl.renderer.GetActiveCamera()
    walls, cpus, mains = [], [], []
    for cam in cams:
        vc.SetPosition(*cam.position)
        vc.SetFocalPoint(*(np.asarray(cam.position) + cam.forward))
        vc.SetViewUp(*cam.up)
        vc.SetViewAngle(cam.fovy)
        vc.SetClippingRange(cam.near, cam.far)
        rw.Render()
        rw.WaitForCompletion()  # warm-up: buffer upload, shader compilation
        for _ in range(reps):
            t0, c0, m0 = time.perf_counter(), time.process_time(), time.thread_time()
            rw.Render()
            rw.WaitForCompletion()
            walls.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
            mains.append(time.thread_time() - m0)
    caps = rw.ReportCapabilities()
    renderer = next((ln.split(":", 1)[1].strip() for ln in caps.splitlines() if "OpenGL renderer string" in ln), "?")
    print(json.dumps({"renderer": renderer, "triangles": int(len(tris)), "wall_s": walls, "cpu_s": cpus, "main_s": mains}))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
