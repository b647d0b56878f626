"""fastenerf: EventNeRF from a colour event camera, trained in seconds.

`kernels/` and `viewer/` live at the repository root (as the design card lays out)
and install as `fastenerf.kernels` and `fastenerf.viewer`.
"""

from setuptools import setup

setup(
    name="fastenerf",
    version="0.1.0",
    description="Fast EventNeRF: radiance fields from a single colour event camera",
    python_requires=">=3.10",
    packages=[
        "fastenerf",
        "fastenerf.data",
        "fastenerf.data.formats",
        "fastenerf.data.synth",
        "fastenerf.fields",
        "fastenerf.commands",
        "fastenerf.kernels",
        "fastenerf.viewer",
    ],
    package_dir={
        "fastenerf": "fastenerf",
        "fastenerf.kernels": "kernels",
        "fastenerf.viewer": "viewer",
    },
    install_requires=[
        # A range, not a pin: the set-up installs torch==2.13.0 first (CPU build on
        # machines without a GPU), and this range must not pull in anything newer.
        "torch>=2.1",
        "warp-lang>=1.5",
        "numpy>=1.24",
        "scipy>=1.10",
        "trimesh>=4.0",
        "moderngl>=5.8",
        "imgui-bundle>=1.5",
        "tqdm>=4.60",
        "imageio>=2.30",
        "scikit-image>=0.21",
        "h5py>=3.8",
        "aedat>=2.0",
        "matplotlib>=3.7",
        "opencv-python-headless>=4.5",
        "xatlas>=0.0.9",
        "pillow>=9.0",
        "fast-simplification>=0.1",
    ],
    extras_require={"dev": ["pytest>=7", "ruff>=0.5"]},
    entry_points={"console_scripts": ["fastenerf=fastenerf.cli:console_main"]},
)
