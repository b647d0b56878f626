"""The mesh scene of our own making: the committed recipe writes a coloured mesh synth can load."""

import numpy as np
import trimesh

from benchmarks.toyset import main, toyset
from fastenerf.cli import main as cli_main


def test_toyset_fits_the_unit_cube_with_three_coloured_parts():
    mesh = toyset()
    assert np.abs(mesh.bounds).max() <= 1.0
    assert len(mesh.split(only_watertight=False)) == 3
    rgb = mesh.visual.vertex_colors[:, :3].astype(float)
    assert rgb.std(axis=0).min() > 10  # stripes and three base colours, not one flat colour


def test_toyset_cli_writes_a_ply_that_keeps_its_colours(tmp_path):
    out = tmp_path / "toyset.ply"
    assert cli_main(["bench", "toyset", str(out)]) == 0
    back = trimesh.load(out, process=False)
    assert len(back.faces) == len(toyset().faces)
    assert np.array_equal(back.visual.vertex_colors, toyset().visual.vertex_colors)


def test_toyset_cli_refuses_to_clobber_or_guess_a_format(tmp_path, capsys):
    folder = tmp_path / "toyset.ply"
    (folder / "keep").mkdir(parents=True)
    assert main([str(folder)]) == 2  # a folder where the mesh file would go: left as it was
    assert (folder / "keep").is_dir()
    assert main([str(tmp_path / "toyset.stl")]) == 2
    assert not (tmp_path / "toyset.stl").exists()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(line.startswith("toyset: error: ") for line in err)
