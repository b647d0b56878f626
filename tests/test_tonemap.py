"""The one exposure / gamma tone map (fastenerf.tonemap) that `fastenerf render`, its videos
and the viewer share."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fastenerf.errors import InputError
from fastenerf.tonemap import Exposure, apply_exposure


def test_viewer_uses_the_same_function():
    import fastenerf.tonemap as shared
    from fastenerf.viewer import frame, tonemap

    assert tonemap.apply_exposure is shared.apply_exposure and tonemap.Exposure is shared.Exposure
    assert frame.apply_exposure is shared.apply_exposure


@pytest.mark.parametrize(
    "kw, name",
    [
        ({"ev": math.nan}, "ev"),
        ({"ev": math.inf}, "ev"),
        ({"ev": 1e6}, "ev"),
        ({"gain": 0.0}, "gain"),
        ({"gain": -1.0}, "gain"),
        ({"gain": math.nan}, "gain"),
        ({"gamma": 1e9}, "gamma"),
        ({"gamma": 0.0}, "gamma"),
    ],
)
def test_bad_exposure_is_one_clear_line(kw, name):
    with pytest.raises(InputError) as e:
        Exposure(**kw).validated("render")
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"render: {name} must be a number in")
    assert Exposure(ev=-6.0, gain=0.25, gamma=4.0).validated() is not None


def test_plus_one_ev_doubles_linear_intensity():
    c = torch.linspace(0.0, 0.7, 50)[:, None].expand(-1, 3)
    out = apply_exposure(c, Exposure(ev=1.0))
    eps = Exposure().eps
    torch.testing.assert_close(out**2.2, 2 * c**2.2 + eps, atol=1e-5, rtol=1e-4)


def read_frames(folder):
    import imageio.v3 as iio

    return np.stack([iio.imread(p) for p in sorted(folder.glob("*.png"))]).astype(np.float64) / 255


def test_render_with_exposure(make_untrained_run, tmp_path, capsys):
    """`fastenerf render --ev 1`: every colour frame twice the linear intensity of the plain
    render (where it does not clip), the background's colour as predicted, the depth maps
    unchanged; bad values get one line."""
    from fastenerf.cli import main as cli

    bg = np.array([0.3, 0.45, 0.6])
    run, _ = make_untrained_run(background=bg.tolist())
    base = ["render", str(run), "--orbit", "2", "--no-progress"]
    assert cli(base + ["--out", str(tmp_path / "a")]) == 0
    assert cli(base + ["--out", str(tmp_path / "b"), "--ev", "1"]) == 0
    a, b = read_frames(tmp_path / "a" / "rgb"), read_frames(tmp_path / "b" / "rgb")
    lit = b < 0.97
    assert lit.mean() > 0.5 and (b >= a).all() and b.mean() > a.mean() + 0.05
    corner = (2 * bg**2.2 + Exposure().eps) ** (1 / 2.2)  # the background, +1 EV
    np.testing.assert_allclose(b[:, 0, 0], np.broadcast_to(corner, (2, 3)), atol=1 / 255)
    # 8-bit frames: half a level of quantisation in each, through x**2.2.
    expect = 2 * a[lit] ** 2.2 + Exposure().eps
    assert np.abs(b[lit] ** 2.2 - expect).max() < 0.012
    np.testing.assert_array_equal(
        read_frames(tmp_path / "a" / "depth"), read_frames(tmp_path / "b" / "depth")
    )
    assert list((tmp_path / "b").glob("video.*"))
    capsys.readouterr()
    for bad in (["--ev", "nan"], ["--gamma", "0"], ["--gain", "1e9"]):
        assert cli(base + ["--out", str(tmp_path / "c"), *bad]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "must be a number in" in err
    assert not (tmp_path / "c").exists()
