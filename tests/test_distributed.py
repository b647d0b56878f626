"""Several processes on the CPU with gloo (issue #21): the fan-out runs every job once, and a
2-rank data-parallel step is the 1-process step on the union of the ranks' batches.

The multi-process tests start real ranks: `torchrun --standalone` for the commands (its free
port, its environment), `torch.multiprocessing` with a file rendezvous for the step test (no
port at all). Each rank runs one torch thread (what torchrun sets): two ranks on a 2-core box.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.multiprocessing as mp

from fastenerf.config import train_preset
from fastenerf.data.formats.native import load_scene
from fastenerf.distributed import World, my_share, share_indices, world_from_env
from fastenerf.errors import InputError
from fastenerf.sampling import RayBatch

ROOT = Path(__file__).resolve().parents[1]
VANILLA_TINY = {
    "depth": 3,
    "width": 32,
    "pos_freqs": 4,
    "dir_freqs": 2,
    "n_coarse": 8,
    "n_fine": 8,
}
TIMEOUT_S = 240


# -- the share of a rank (no processes) ---------------------------------------------------------


def test_round_robin_share_covers_every_job_once():
    for n in range(0, 9):
        for size in (1, 2, 3, 4):
            shares = share_indices(n, size)
            flat = sorted(i for s in shares for i in s)
            assert flat == list(range(n))
            assert max(map(len, shares)) - min(map(len, shares)) <= 1


def test_cost_share_balances_and_keeps_job_order():
    costs = [480, 300, 480, 300, 480, 300, 60]  # a study's vanilla/ngp budgets
    shares = share_indices(len(costs), 2, costs)
    assert sorted(i for s in shares for i in s) == list(range(len(costs)))
    loads = [sum(costs[i] for i in s) for s in shares]
    assert max(loads) - min(loads) <= max(costs)
    assert all(s == sorted(s) for s in shares)
    jobs = [f"job{i}" for i in range(len(costs))]
    by_rank = [
        my_share(jobs, World(r, 2, r, True), cost=lambda j: costs[jobs.index(j)]) for r in (0, 1)
    ]
    assert by_rank == [[jobs[i] for i in s] for s in shares]


def test_world_from_env():
    assert world_from_env({}) == World()
    w = world_from_env({"RANK": "3", "WORLD_SIZE": "4", "LOCAL_RANK": "1"})
    assert (w.rank, w.size, w.local_rank, w.distributed, w.is_main) == (3, 4, 1, True, False)
    with pytest.raises(InputError, match="rank must be in"):
        world_from_env({"RANK": "4", "WORLD_SIZE": "4"})
    with pytest.raises(InputError, match="integers"):
        world_from_env({"RANK": "x", "WORLD_SIZE": "2"})


# -- real ranks ---------------------------------------------------------------------------------


def _env() -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1", FASTENERF_PROGRESS="0")
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    return env


def torchrun(args: list[str], nproc: int = 2) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone"]
    cmd += [f"--nproc-per-node={nproc}", "-m", "fastenerf.cli", *args]
    return subprocess.run(
        cmd, cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=TIMEOUT_S
    )


TRAIN_FLAGS = ["--steps", "3", "--rays", "16", "--device", "cpu", "--no-progress"]
TRAIN_FLAGS += ["--options", json.dumps(VANILLA_TINY)]


def test_train_many_runs_every_job_once_over_two_ranks(tiny_scene, tmp_path):
    scenes = []
    for name in ("a", "b", "c"):  # three jobs: one scene under three names
        (tmp_path / name).symlink_to(tiny_scene, target_is_directory=True)
        scenes.append(str(tmp_path / name))
    out = tmp_path / "many"
    r = torchrun(["train-many", *scenes, "--out", str(out), "--backends", "vanilla", *TRAIN_FLAGS])
    assert r.returncode == 0, r.stderr[-3000:]
    summary = json.loads((out / "train_many.json").read_text())
    rows = summary["runs"]
    assert summary["world_size"] == 2
    assert [row["label"] for row in rows] == ["a", "b", "c"]
    assert sorted(row["rank"] for row in rows) == [0, 0, 1]  # round-robin: a, c on 0; b on 1
    assert all(row["status"] == "trained" and row["steps"] == 3 for row in rows)
    assert all(np.isfinite(row["psnr"]) for row in rows)
    assert sorted(p.name for p in (out / "runs").iterdir()) == [f"{n}-vanilla" for n in "abc"]
    for name in "abc":
        run = out / "runs" / f"{name}-vanilla"
        steps = [json.loads(x)["step"] for x in (run / "metrics.jsonl").read_text().splitlines()]
        assert steps == [1, 2, 3]  # trained once: a second training would log again
        assert json.loads((run / "progress.json").read_text())["finished"]
    md = (out / "train_many.md").read_text()
    assert all(f"| {n} | vanilla | trained | 3 |" in md for n in "abc")

    # --resume in one process (no torchrun): finished runs are skipped, nothing retrained
    from fastenerf.cli import main

    before = {p: p.stat().st_mtime_ns for p in out.rglob("checkpoint.pt")}
    assert (
        main(
            [
                "train-many",
                *scenes,
                "--out",
                str(out),
                "--backends",
                "vanilla",
                "--resume",
                *TRAIN_FLAGS,
            ]
        )
        == 0
    )
    rows = json.loads((out / "train_many.json").read_text())["runs"]
    assert [row["status"] for row in rows] == ["skipped"] * 3
    assert {p: p.stat().st_mtime_ns for p in out.rglob("checkpoint.pt")} == before
    # without --resume an existing run is refused before any training
    assert (
        main(["train-many", *scenes, "--out", str(out), "--backends", "vanilla", *TRAIN_FLAGS]) == 2
    )


def test_train_data_parallel_writes_one_run_folder(tiny_scene, tmp_path):
    out = tmp_path / "run"
    r = torchrun(
        [
            "train",
            str(tiny_scene),
            "--out",
            str(out),
            "--backend",
            "vanilla",
            "--data-parallel",
            *TRAIN_FLAGS,
        ]
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.count("training vanilla") == 1  # rank 1 prints nothing
    record = json.loads((out / "data_parallel.json").read_text())["starts"]
    assert record == [
        {
            "step": 0,
            "world_size": 2,
            "backend": "gloo",
            "rays_per_step_per_rank": 16,
            "rays_per_step_total": 32,
        }
    ]
    assert json.loads((out / "progress.json").read_text())["step"] == 3


# -- a data-parallel step is the union batch's step ---------------------------------------------


def tiny_cfg(**kw):
    base = dict(
        steps=1,
        rays_per_step=16,
        windows_per_step=2,
        eval_every_s=0,
        checkpoint_every_s=0,
        device="cpu",
        lr=1e-2,
        backend_options=dict(VANILLA_TINY),
    )
    base.update(kw)
    return train_preset("fast", "vanilla", **base)


def deterministic_render(field) -> None:
    """Render with fixed sample positions (train=False): the jitter, drawn per ray from the
    global RNG, differs between 2 x B rays and one draw of 2B, which is not what is tested."""
    render = field.render
    field.render = lambda *a, **k: render(*a, **{**k, "train": False})


def peek_batch(trainer) -> RayBatch:
    """The batch the next step will draw (the sampler is put back where it was)."""
    state = trainer.sampler.state_dict()
    batch = trainer.sampler.sample()
    trainer.sampler.load_state_dict(state)
    return batch


def _rank(rank: int, world_size: int, scene_dir: str, tmp: str) -> None:
    torch.set_num_threads(1)
    from fastenerf.data_parallel import make_data_parallel
    from fastenerf.distributed import destroy, init
    from fastenerf.train import Trainer

    world = init("gloo", rank=rank, world_size=world_size, init_method=f"file://{tmp}/rdzv")
    trainer = Trainer(load_scene(scene_dir), tiny_cfg(), f"{tmp}/rank{rank}")
    if rank == 1:  # its own initial weights: the broadcast must replace them with rank 0's
        with torch.no_grad():
            for p in trainer.field.parameters():
                p.add_(torch.randn_like(p))
    deterministic_render(trainer.field)
    sync = make_data_parallel(trainer, world)
    batch = peek_batch(trainer)
    stats = trainer.step()
    sync.after_step(trainer, stats)
    grads = {n: p.grad.clone() for n, p in trainer.field.named_parameters() if p.grad is not None}
    weights = {k: v.clone() for k, v in trainer.field.state_dict().items()}
    # step 2: rank 1's loss is NaN; it skips backward, yet both ranks must meet and skip
    if rank == 1:
        bad = peek_batch(trainer)
        bad.target = bad.target * float("nan")
        trainer.sampler.sample = lambda: bad
    trainer.cfg.steps = 2
    summary = trainer.run([sync], progress=False)
    torch.save(
        {
            "batch": batch.__dict__,
            "loss": stats["loss"],
            "weights": weights,
            "grads": grads,
            "nan_step": {
                "steps": summary["steps"],
                "skipped_steps": trainer.skipped_steps,
                "unchanged": all(
                    torch.equal(v, weights[k]) for k, v in trainer.field.state_dict().items()
                ),
            },
        },
        f"{tmp}/rank{rank}.pt",
    )
    destroy()


def two_ranks(target, scene_dir, tmp_path, saved: str) -> tuple[dict, dict]:
    """Run `target(rank, 2, scene_dir, tmp)` in two spawned processes (gloo over a file
    rendezvous); returns what each saved to tmp/`saved`RANK.pt."""
    ctx = mp.get_context("spawn")
    procs = [ctx.Process(target=target, args=(r, 2, str(scene_dir), str(tmp_path))) for r in (0, 1)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(TIMEOUT_S)
    assert [p.exitcode for p in procs] == [0, 0]
    return tuple(torch.load(tmp_path / f"{saved}{r}.pt", weights_only=False) for r in (0, 1))


def union(a: RayBatch, b: RayBatch) -> RayBatch:
    """One batch holding both: rows :B are every pixel at t0, rows B: at t1."""
    ba, bb = len(a.target), len(b.target)
    cat = torch.cat
    return RayBatch(
        cat([a.rays_o[:ba], b.rays_o[:bb], a.rays_o[ba:], b.rays_o[bb:]]),
        cat([a.rays_d[:ba], b.rays_d[:bb], a.rays_d[ba:], b.rays_d[bb:]]),
        cat([a.pix, b.pix]),
        None if a.channel is None else cat([a.channel, b.channel]),
        cat([a.target, b.target]),
        cat([a.positive, b.positive]),
        a.n_windows + b.n_windows,
    )


def test_two_rank_step_equals_one_process_step_on_the_union_batch(tiny_scene, tmp_path):
    from fastenerf.train import Trainer

    r0, r1 = two_ranks(_rank, tiny_scene, tmp_path, "rank")
    a, b = RayBatch(**r0["batch"]), RayBatch(**r1["batch"])
    assert not torch.equal(a.pix, b.pix)  # the ranks drew their own rays

    one = Trainer(load_scene(tiny_scene), tiny_cfg(), tmp_path / "one")
    deterministic_render(one.field)
    assert torch.equal(peek_batch(one).pix, a.pix)  # rank 0 draws what one process draws
    u = union(a, b)
    one.sampler.sample = lambda: u
    stats = one.step()

    assert stats["loss"] == pytest.approx((r0["loss"] + r1["loss"]) / 2, rel=1e-5)
    for name, p in one.field.named_parameters():
        torch.testing.assert_close(r0["grads"][name], p.grad, rtol=1e-4, atol=1e-7)
        torch.testing.assert_close(r1["grads"][name], p.grad, rtol=1e-4, atol=1e-7)
    # Adam's first update is lr·g/(|g| + eps): scale-free (so the gradients are compared above),
    # and for a gradient near eps it moves by up to lr times the gradient's rounding error.
    lr = one.cfg.lr
    for name, w in one.field.state_dict().items():
        torch.testing.assert_close(r0["weights"][name], w, rtol=0, atol=1e-3 * lr)
        torch.testing.assert_close(r1["weights"][name], w, rtol=0, atol=1e-3 * lr)
    # a non-finite loss on one rank: no deadlock, and no rank updates (as one process would not)
    for r in (r0, r1):
        assert r["nan_step"] == {"steps": 2, "skipped_steps": 1, "unchanged": True}


def test_a_rank_that_left_its_group_exits_at_once_with_its_code():
    """console_main after a group was left: os._exit with main's code, output flushed first."""
    code = (
        "import sys; from fastenerf import distributed as d; d._left = True; "
        "sys.argv = ['fastenerf', 'info', '/nonexistent/scene']; "
        "print('before', flush=False); from fastenerf.cli import console_main; console_main()"
    )
    r = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, env=_env(), capture_output=True, text=True
    )
    assert r.returncode == 2
    assert r.stdout.strip() == "before"  # flushed although os._exit skips the teardown
    err = [x for x in r.stderr.splitlines() if "Warp CUDA warning" not in x]
    assert err == ["fastenerf info: error: /nonexistent/scene: no such file or folder"]


def _rank_poses(rank: int, world_size: int, scene_dir: str, tmp: str) -> None:
    torch.set_num_threads(1)
    from fastenerf.data_parallel import make_data_parallel
    from fastenerf.distributed import destroy, init
    from fastenerf.train import Trainer

    world = init("gloo", rank=rank, world_size=world_size, init_method=f"file://{tmp}/rdzv")
    cfg = tiny_cfg(steps=6, refine_poses=True, refine_start=0.0, refine_warmup=0.0)
    cfg.refine_gate, cfg.refine_lr = 0.0, 1e-2  # every seen row steps, and visibly
    trainer = Trainer(load_scene(scene_dir), cfg, f"{tmp}/rank{rank}")
    sync = make_data_parallel(trainer, world)
    seen = []
    pose_cal = trainer.selfcal.pose_cal
    step = pose_cal.step
    pose_cal.step = lambda found_inf: (seen.append(pose_cal.seen.clone()), step(found_inf))
    trainer.run([sync], progress=False)
    torch.save(
        {
            "delta": pose_cal.refiner.delta.detach().clone(),
            "moments": {
                k: v.clone()
                for k, v in pose_cal.optimizer.state[pose_cal.refiner.delta].items()
                if torch.is_tensor(v)
            },
            "seen": torch.stack(seen),
        },
        f"{tmp}/poses{rank}.pt",
    )
    destroy()


def test_two_ranks_refine_one_set_of_poses(tiny_scene, tmp_path):
    """Data-parallel with --refine-poses: the corrections' gradients are averaged and every
    rank's row Adam steps the rows any rank saw, so the ranks' corrections and moments stay
    the same (each rank's own, from its own rays, drift apart)."""
    r0, r1 = two_ranks(_rank_poses, tiny_scene, tmp_path, "poses")
    assert torch.equal(r0["seen"], r1["seen"])  # the union, on both
    assert r0["delta"].abs().max() > 0  # the poses moved
    torch.testing.assert_close(r0["delta"], r1["delta"], rtol=0, atol=0)
    for k, v in r0["moments"].items():
        torch.testing.assert_close(v, r1["moments"][k], rtol=0, atol=0)
