"""Chequerboard calibration (supplement A.1): inner corners -> lens -> one camera pose per frame.

The poses feed the turntable fit (`fastenerf.data.calibrate.fit_turntable`). OpenCV does the
vision: `findChessboardCorners` + `cornerSubPix` (corners), `calibrateCamera` (intrinsics and
radial distortion k1, k2, when none are given), `solvePnP` (IPPE, refined by Levenberg-Marquardt)
for each frame.

Conventions:
- Board: COLS x ROWS *inner* corners (a board of 10 x 7 squares is 9 x 6), squares of side
  `square` (world units, e.g. metres). The board frame has its origin at the board's centre,
  x along a row to the right seen from the printed side, y up along a column, z out of the
  printed side. Which way is "up" is read from the image: the board's +y is the grid
  direction that points up in the frame (an upright camera; a board standing on a turntable).
- Poses: OpenCV camera-to-world (x right, y down, z forward) in the board frame (M, 4, 4).
- Pixels: the project's convention, pixel centres at +0.5 (DESIGN §9); OpenCV's corners
  (centres at integers) are shifted by +0.5 on detection, so K is the project's K.
- Distortion: the "opencv" radial model (x_d = x_u (1 + k1 r² + k2 r⁴)), tangential terms and
  k3 held at zero (what the project's rays model); a given EventNeRF "division" model is
  undistorted exactly before PnP.
"""

from __future__ import annotations

import math
import re
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import IntrinsicsConfig
from ..errors import InputError

MIN_FRAMES = 5  # the turntable fit's minimum; lens calibration wants more (see the docs)
MAX_LENS_VIEWS = 40  # calibrateCamera's cost grows with views; 40 spread ones pin a lens
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")
TIMESTAMPS_FILE = "timestamps.txt"


@dataclass(frozen=True)
class Board:
    """A chequerboard: cols x rows inner corners, squares of side `square` (world units)."""

    cols: int
    rows: int
    square: float

    @classmethod
    def parse(cls, text: str, square: float) -> Board:
        """From "COLSxROWS" (e.g. "9x6") and the square's side; one-line errors."""
        m = re.fullmatch(r"\s*(\d+)\s*[xX×]\s*(\d+)\s*", str(text))
        if not m:
            raise InputError(f"--board {text!r}: expected COLSxROWS inner corners, e.g. 9x6")
        cols, rows = int(m[1]), int(m[2])
        if min(cols, rows) < 3:
            raise InputError(f"--board {text}: needs at least 3x3 inner corners")
        if not (math.isfinite(square) and square > 0):
            raise InputError(f"--square {square}: must be a positive length (world units)")
        return cls(cols, rows, float(square))

    def object_points(self) -> np.ndarray:
        """(rows * cols, 3) float64 corner positions in the board frame, row-major from the
        top-left corner seen from the printed side (row r, column c)."""
        r, c = np.mgrid[0 : self.rows, 0 : self.cols]
        x = (c - (self.cols - 1) / 2) * self.square
        y = ((self.rows - 1) / 2 - r) * self.square
        return np.stack([x, y, np.zeros_like(x)], -1).reshape(-1, 3).astype(np.float64)

    def __str__(self) -> str:
        return f"{self.cols}x{self.rows}"


@dataclass
class Detections:
    """Boards found in a frame source.

    names: (M,) frame names (file names, or "frame N" of a recording); index: (M,) int
    positions in the source; t_us: (M,) int64 µs or None (no times); corners: (M, N, 2) float64
    pixels (centres at +0.5), ordered as `Board.object_points`; size: (width, height);
    n_frames: frames looked at; n_found: boards found (M before any rejection).
    """

    names: list[str]
    index: np.ndarray
    t_us: np.ndarray | None
    corners: np.ndarray
    size: tuple[int, int]
    n_frames: int
    n_found: int

    def take(self, keep: np.ndarray) -> Detections:
        """The detections at boolean mask / indices `keep`."""
        idx = np.arange(len(self.names))[keep]
        return Detections(
            [self.names[i] for i in idx],
            self.index[idx],
            None if self.t_us is None else self.t_us[idx],
            self.corners[idx],
            self.size,
            self.n_frames,
            self.n_found,
        )


# ----------------------------------------------------------------------------------- frames


def iter_frames(src: str | Path, every: int = 1) -> Iterator[tuple[str, int | None, np.ndarray]]:
    """(name, t_us or None, gray (H, W) uint8) for every `every`-th frame of `src`.

    src: a folder of images (sorted by name; with a `timestamps.txt` of lines `FILE T_US`, as
    `fastenerf import --frames` writes, those files in that order with their times) or an
    AEDAT4 recording (its APS frames, times on DV's clock, µs). One-line errors.
    """
    p = Path(src)
    if p.is_dir():
        items = _folder_items(p)
        for i, (f, t) in enumerate(items):
            if i % every == 0:
                yield f.name, t, _read_gray(f)
    elif p.suffix.lower() == ".aedat4":
        from .formats.aedat import iter_aedat4_frames

        for i, fr in enumerate(iter_aedat4_frames(p)):
            if i % every == 0:
                yield f"frame {i}", fr.t_us, to_gray8(fr.rgb())
    elif p.exists():
        raise InputError(f"{p}: not a folder of images or an .aedat4 recording")
    else:
        raise InputError(f"{p}: no such folder or AEDAT4 file")


def _folder_items(p: Path) -> list[tuple[Path, int | None]]:
    ts = p / TIMESTAMPS_FILE
    if not ts.is_file():
        return [(f, None) for f in sorted(p.iterdir()) if f.suffix.lower() in IMAGE_SUFFIXES]
    items = []
    for n, line in enumerate(ts.read_text().splitlines(), 1):
        parts = line.split("#", 1)[0].split()
        if not parts:
            continue
        try:
            items.append((p / parts[0], int(parts[1])))
        except (IndexError, ValueError):
            raise InputError(f"{ts}:{n}: expected 'FILE T_US' (integer µs)") from None
        if not items[-1][0].is_file():
            raise InputError(f"{ts}:{n}: {parts[0]} not found in {p}")
    return items


def _read_gray(f: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise InputError(f"{f}: not a readable image")
    return img


def to_gray8(img: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, 3|4) RGB(A), uint8 or uint16 -> (H, W) uint8 luma."""
    img = np.asarray(img)
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    if img.ndim == 3:
        rgb = img[..., :3].astype(np.float32)
        img = np.clip(rgb @ np.array([0.299, 0.587, 0.114], np.float32) + 0.5, 0, 255)
    return img.astype(np.uint8)


# ---------------------------------------------------------------------------------- corners


def detect_corners(gray: np.ndarray, board: Board) -> np.ndarray | None:
    """Inner corners of `board` in a gray uint8 image: (rows * cols, 2) float64 pixels
    (centres at +0.5), sub-pixel refined, in `Board.object_points` order; None if not found."""
    import cv2

    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
    ok, c = cv2.findChessboardCorners(gray, (board.cols, board.rows), flags=flags)
    if not ok or c is None or len(c) != board.cols * board.rows:
        return None
    grid = _orient(c.reshape(board.rows, board.cols, 2).astype(np.float64), board)
    if grid is None:
        return None
    pts = grid.reshape(-1, 1, 2).astype(np.float32)
    # Half-window below half a square's side, so the window never reaches the next corner.
    step = min(
        np.linalg.norm(np.diff(grid, axis=0), axis=-1).min(),
        np.linalg.norm(np.diff(grid, axis=1), axis=-1).min(),
    )
    win = int(np.clip(step * 0.4, 2, 11))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    pts = cv2.cornerSubPix(gray, pts, (win, win), (-1, -1), crit)
    return pts.reshape(-1, 2).astype(np.float64) + 0.5


def _orient(grid: np.ndarray, board: Board) -> np.ndarray | None:
    """Reorder a detected (rows, cols, 2) grid to the board convention: seen from the printed
    side (x right, y up: the grid's rows run right, its +y points up in the image).

    OpenCV's order may start at any corner of the grid (and, for a square grid, run along
    either side); of the orderings that keep the grid's shape, take those that see the
    printed side (a right-handed x, y in the image, whose y is down) and of these the one
    whose y points most nearly up.
    """
    cands = [grid, grid[::-1], grid[:, ::-1], grid[::-1, ::-1]]
    if board.cols == board.rows:
        cands += [g.transpose(1, 0, 2) for g in cands]
    best, best_up = None, -np.inf
    for g in cands:
        if g.shape[:2] != (board.rows, board.cols):
            continue
        x = (g[:, -1] - g[:, 0]).mean(0)  # along a row, to the right
        y = (g[0] - g[-1]).mean(0)  # up a column (row 0 is the top)
        if x[0] * y[1] - x[1] * y[0] >= 0:  # image y is down: the printed side has x × y < 0
            continue
        up = -y[1] / (np.linalg.norm(y) + 1e-12)
        if up > best_up:
            best, best_up = g, up
    return best


def find_boards(
    src: str | Path, board: Board, every: int = 1, progress: bool = False
) -> Detections:
    """Detect `board` in every `every`-th frame of `src` (see `iter_frames`).

    Frames without a board are counted and skipped. One-line errors for a source with no
    frames or frames of different sizes.
    """
    from tqdm import tqdm

    names, index, times, corners = [], [], [], []
    size = None
    n = 0
    frames = iter_frames(src, every)
    for i, (name, t, gray) in enumerate(
        tqdm(frames, desc="chequerboard", unit="frame", disable=not progress, leave=False)
    ):
        n += 1
        hw = (gray.shape[1], gray.shape[0])
        if size is None:
            size = hw
        elif hw != size:
            raise InputError(
                f"{src}: {name} is {hw[0]}x{hw[1]}, the first frame {size[0]}x{size[1]}"
            )
        c = detect_corners(gray, board)
        if c is None:
            continue
        names.append(name)
        index.append(i * every)
        times.append(t)
        corners.append(c)
    if n == 0:
        what = (
            f"no images ({', '.join(IMAGE_SUFFIXES)}) in this folder"
            if Path(src).is_dir()
            else "the recording's frame stream has no frames"
        )
        raise InputError(f"{src}: {what}")
    have_t = len(times) > 0 and all(t is not None for t in times)
    return Detections(
        names,
        np.asarray(index, np.int64),
        np.asarray(times, np.int64) if have_t else None,
        np.asarray(corners, np.float64).reshape(len(corners), board.rows * board.cols, 2),
        size,
        n,
        len(names),
    )


def require_frames(det: Detections, src: str | Path, board: Board, rejected: int = 0) -> None:
    """One-line error when fewer than `MIN_FRAMES` frames are usable (`rejected` of the
    found ones were dropped for their reprojection error)."""
    m, n = len(det.names), det.n_frames
    if det.n_found == 0:
        where = "the only frame" if n == 1 else f"any of {n} frames"
        raise InputError(
            f"{src}: board {board} not found in {where} (--board counts inner corners: 9x6 "
            "for a board of 10x7 squares)"
        )
    if m < MIN_FRAMES:
        why = f", {rejected} of them rejected (reprojection error)" if rejected else ""
        raise InputError(
            f"{src}: board {board} found in only {det.n_found} of {_frames(n)}{why}; the "
            f"calibration needs at least {MIN_FRAMES} usable frames"
        )


def _frames(n: int) -> str:
    return f"{n} frame" + ("" if n == 1 else "s")


# ------------------------------------------------------------------------------ lens, poses


def calibrate_lens(det: Detections, board: Board) -> tuple[IntrinsicsConfig, float]:
    """Intrinsics and radial distortion (k1, k2) by `cv2.calibrateCamera` from up to
    `MAX_LENS_VIEWS` detections spread over the source. Returns (intrinsics, RMS
    reprojection error in pixels)."""
    import cv2

    m = len(det.names)
    pick = np.unique(np.linspace(0, m - 1, min(m, MAX_LENS_VIEWS)).round().astype(int))
    obj = [board.object_points().astype(np.float32)] * len(pick)
    img = [det.corners[i].astype(np.float32).reshape(-1, 1, 2) for i in pick]
    flags = cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3
    try:
        rms, K, dist, *_ = cv2.calibrateCamera(obj, img, det.size, None, None, flags=flags)
    except cv2.error as e:
        raise InputError(f"lens calibration failed ({str(e).strip().splitlines()[-1]})") from None
    d = np.ravel(dist)
    intr = IntrinsicsConfig(
        fx=float(K[0, 0]),
        fy=float(K[1, 1]),
        cx=float(K[0, 2]),
        cy=float(K[1, 2]),
        k1=float(d[0]),
        k2=float(d[1]),
        distortion_model="opencv",
    )
    if not all(np.isfinite([intr.fx, intr.fy, intr.cx, intr.cy])) or min(intr.fx, intr.fy) <= 0:
        raise InputError("lens calibration failed (no finite focal length: too few board views?)")
    return intr, float(rms)


def board_poses(
    det: Detections, board: Board, intr: IntrinsicsConfig
) -> tuple[np.ndarray, np.ndarray]:
    """One PnP pose per detection. Returns c2w (M, 4, 4) OpenCV camera-to-world in the board
    frame (world units of `board.square`) and the RMS reprojection error per frame (M,) px."""
    import cv2

    from .rig import Intrinsics

    cam = Intrinsics.from_config(intr, *det.size)
    obj = board.object_points()
    K = cam.K
    if intr.distortion_model == "opencv":
        dist = np.array([intr.k1, intr.k2, 0.0, 0.0])
    else:  # the division model has an exact inverse: undistort, then a plain pinhole
        dist = np.zeros(4)
    c2w = np.tile(np.eye(4), (len(det.names), 1, 1))
    rms = np.zeros(len(det.names))
    for i, uv in enumerate(det.corners):
        if intr.distortion_model != "opencv":
            xy = cam.undistort((uv - [intr.cx, intr.cy]) / [intr.fx, intr.fy])
            uv = xy * [intr.fx, intr.fy] + [intr.cx, intr.cy]
        ok, rvec, tvec = cv2.solvePnP(obj, uv.reshape(-1, 1, 2), K, dist, flags=cv2.SOLVEPNP_IPPE)
        if not ok:
            rms[i] = np.inf
            continue
        rvec, tvec = cv2.solvePnPRefineLM(obj, uv.reshape(-1, 1, 2), K, dist, rvec, tvec)
        proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
        rms[i] = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - uv) ** 2, -1))))
        R, _ = cv2.Rodrigues(rvec)
        c2w[i, :3, :3] = R.T
        c2w[i, :3, 3] = -R.T @ tvec.ravel()
    return c2w, rms


def reject_outliers(rms: np.ndarray, floor_px: float = 1.0, factor: float = 5.0) -> np.ndarray:
    """Boolean mask of poses to keep: reprojection RMS below max(floor, factor · median)
    (a misdetected grid reprojects badly; a good one sits at the corner noise)."""
    finite = rms[np.isfinite(rms)]
    if len(finite) == 0:
        return np.zeros(len(rms), bool)
    return np.isfinite(rms) & (rms <= max(floor_px, factor * float(np.median(finite))))


@dataclass
class BoardPoses:
    """What `poses_from_chequerboard` found: the usable detections, their poses c2w (M, 4, 4)
    (board frame, OpenCV camera-to-world), reprojection RMS (M,) px, the intrinsics used,
    the lens calibration's RMS (px; None when the intrinsics were given) and how many found
    boards were rejected for their reprojection error."""

    detections: Detections
    c2w: np.ndarray
    rms_px: np.ndarray
    intrinsics: IntrinsicsConfig
    lens_rms_px: float | None
    rejected: int


def poses_from_chequerboard(
    src: str | Path,
    board: Board,
    intrinsics: str | Path | None = None,
    every: int = 1,
    progress: bool = False,
) -> BoardPoses:
    """Chequerboard frames -> camera poses: detect the board in every `every`-th frame of
    `src` (folder of images or AEDAT4 recording), calibrate the lens unless an `intrinsics`
    file is given (`fastenerf.data.intrinsics` formats), one PnP pose per frame, rejecting
    misdetections. One-line errors for no frames / too few usable frames."""
    from .intrinsics import read_intrinsics

    det = find_boards(src, board, every, progress)
    require_frames(det, src, board)
    lens_rms = None
    if intrinsics is not None:
        intr = read_intrinsics(intrinsics, *det.size)
    else:
        intr, lens_rms = calibrate_lens(det, board)
    c2w, rms = board_poses(det, board, intr)
    keep = reject_outliers(rms)
    rejected = int((~keep).sum())
    det, c2w, rms = det.take(keep), c2w[keep], rms[keep]
    require_frames(det, src, board, rejected)
    if rejected and intrinsics is None:
        # The misdetections pulled the lens fit too: calibrate again without them.
        intr, lens_rms = calibrate_lens(det, board)
        c2w, rms = board_poses(det, board, intr)
    return BoardPoses(det, c2w, rms, intr, lens_rms, rejected)


def read_frame(src: str | Path, index: int) -> np.ndarray:
    """Gray frame number `index` (0-based, every frame counted) of `src`, for pictures."""
    for i, (_, _, gray) in enumerate(iter_frames(src)):
        if i == index:
            return gray
    raise InputError(f"{src}: has no frame {index}")


def board_outline(board: Board, per_side: int = 16) -> np.ndarray:
    """(4 * per_side + 1, 3) points along the edge of the squares, board frame (closed)."""
    hx, hy = (board.cols + 1) / 2 * board.square, (board.rows + 1) / 2 * board.square
    corners = np.array([[-hx, hy], [hx, hy], [hx, -hy], [-hx, -hy], [-hx, hy]])
    a = np.linspace(0.0, 1.0, per_side, endpoint=False)[:, None]
    sides = zip(corners[:-1], corners[1:], strict=True)
    pts = np.concatenate([c0 + a * (c1 - c0) for c0, c1 in sides])
    pts = np.concatenate([pts, corners[:1]])
    return np.concatenate([pts, np.zeros((len(pts), 1))], -1)


def project(
    points: np.ndarray, c2w: np.ndarray, intr: IntrinsicsConfig, size: tuple[int, int]
) -> np.ndarray:
    """World points (N, 3) -> pixels (N, 2) (centres at +0.5) of the camera c2w (4, 4)
    through the lens `intr` (distortion included)."""
    from .rig import Intrinsics

    w2c = np.linalg.inv(c2w)
    p = np.asarray(points, np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
    return Intrinsics.from_config(intr, *size).project(p)


def progress_enabled() -> bool:
    """Progress bars only when someone watches (a terminal)."""
    return sys.stderr.isatty()


# -------------------------------------------------------------------------------- synthetic


def render_chequerboard(
    board: Board,
    intr: IntrinsicsConfig,
    size: tuple[int, int],
    c2w: np.ndarray,
    noise: float = 2.0,
    blur_px: float = 0.7,
    supersample: int = 1,
    seed: int = 0,
) -> np.ndarray:
    """Gray frames (M, H, W) uint8 of `board` (on white paper, half a square of margin, in
    front of a darker shaded wall) seen by cameras c2w (M, 4, 4) (board frame, OpenCV) through
    the lens `intr` (its distortion included), for tests and demonstrations.

    Each pixel is the mean of supersample² rays, each box-filtered across the squares' edges
    (their footprint on the board), so edges are anti-aliased and corners sit where the lens
    puts them to a few hundredths of a pixel; then a Gaussian blur of `blur_px` (σ, pixels:
    the optics) and Gaussian noise of σ `noise` grey levels.
    """
    import cv2

    from .rig import Intrinsics

    w, h = size
    s = supersample
    u, v = np.meshgrid((np.arange(w * s) + 0.5) / s, (np.arange(h * s) + 0.5) / s)
    d_cam = Intrinsics.from_config(intr, w, h).pixel_to_camera(u.ravel(), v.ravel())
    d_cam = d_cam.astype(np.float32)
    # The wall behind: a smooth shade, so the background is not a flat colour.
    wall = (70.0 + 30.0 * (u / w) + 20.0 * (v / h)).astype(np.float32).ravel()
    hx, hy = (board.cols + 1) / 2 * board.square, (board.rows + 1) / 2 * board.square
    rng = np.random.default_rng(seed)
    out = np.empty((len(c2w), h, w), np.uint8)
    for i, pose in enumerate(np.asarray(c2w, np.float64)):
        R, o = pose[:3, :3].astype(np.float32), pose[:3, 3]
        dw = d_cam @ R.T  # (P, 3) world directions
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = np.float32(-o[2]) / dw[:, 2]
        lam[~(lam > 0)] = np.inf  # rays that never reach the board's plane
        x = o[0] + lam * dw[:, 0]
        y = o[1] + lam * dw[:, 1]
        # Column / row coordinates (square boundaries at integers, row 0 at the top) and
        # each sample's footprint in them, for a box filter across every square edge.
        U = ((x + hx) / board.square).reshape(h * s, w * s)
        V = ((hy - y) / board.square).reshape(h * s, w * s)
        with np.errstate(invalid="ignore"):
            fu = np.abs(np.gradient(U, axis=0)) + np.abs(np.gradient(U, axis=1))
            fv = np.abs(np.gradient(V, axis=0)) + np.abs(np.gradient(V, axis=1))
        img = wall.copy().reshape(h * s, w * s)
        paper = (U > -0.5) & (U < board.cols + 1.5) & (V > -0.5) & (V < board.rows + 1.5)
        img[paper] = 225.0
        sq = (U > 0) & (U < board.cols + 1) & (V > 0) & (V < board.rows + 1)
        # Top-left square dark, as OpenCV's printed pattern: dark where gu · gv = +1.
        gu = _box_step(U[sq], fu[sq], board.cols)
        img[sq] = 125.0 - 100.0 * gu * _box_step(V[sq], fv[sq], board.rows)
        img = img.reshape(h, s, w, s).mean((1, 3))
        if blur_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur_px)
        img = img + rng.normal(0.0, noise, img.shape)
        out[i] = np.clip(img + 0.5, 0, 255).astype(np.uint8)
    return out


def _box_step(u: np.ndarray, footprint: np.ndarray, n: int) -> np.ndarray:
    """sign(sin(π u)) (+1 on even squares, -1 on odd) box-filtered over `footprint` (same
    units) across the inner edges u = 1..n: linear within half a footprint of each, so an
    edge shades a pixel by the fraction of it on either side."""
    d = np.abs(u - np.clip(np.round(u), 1, n))  # distance to the nearest inner edge
    sign = np.where(np.floor(u) % 2 == 0, 1.0, -1.0)
    return sign * np.clip(2.0 * d / np.maximum(footprint, 1e-9), 0.0, 1.0)
