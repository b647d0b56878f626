"""Interactive viewer (installed as `fastenerf.viewer`).

camera.py    OrbitCamera (orbit / pan / zoom / snap), intrinsics from a field of view, camera paths
tonemap.py   exposure in log space, depth / opacity colouring, 8-bit
autoscale.py resolution scale that holds a frame rate while moving and refines when still
frame.py     one frame: render_raw (through fastenerf.render.render_image) and shade
blit.py      GL: FrameTexture (pinned upload), Offscreen, headless EGL snapshot
worker.py    background render thread for the window
framecache.py the frame shown: re-shade it, or ask the worker for a new render
source.py    what is viewed: a run on disk, live training (TrainThread), or a field
panels.py    the window's control panel, one function per section
controls.py  mouse drag and wheel over the view -> orbit / pan / zoom
app.py       the imgui-bundle window (Viewer, run_app)
bench.py     bench_viewer / bench_upload
"""
