"""The graphed training step (issue #17) takes the device path's steps.

On the CPU nothing is captured: the graph's body runs eagerly on the same static buffers, with
the learning rate as a tensor and the jitter drawn outside the body, and must match the plain
path up to float32 rounding (tests/same_steps.py: the last bit on some CPUs). Where CUDA is
present the same checks run with the step captured and replayed (the GPU's atomics make the
hash-grid gradients order-dependent, so there the losses agree to a tolerance). An overflowing
sample buffer is flagged on either path, never truncated silently.
"""

import math

import pytest
import torch

from fastenerf.data.formats.native import load_scene
from fastenerf.errors import InputError
from fastenerf.graph_step import KEEP_FREE_SHARE, WARMUP, GraphedStep
from fastenerf.train import Trainer
from tests.same_steps import assert_same_losses, assert_same_tensor
from tests.test_train import NGP_TINY, tiny_cfg

CUDA = torch.cuda.is_available()
DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not CUDA, reason="no CUDA"))]


@pytest.fixture(scope="module")
def scene(tiny_scene):
    return load_scene(tiny_scene)


def make(scene, path, mode: str, device: str = "cpu", capture=None, **kw) -> Trainer:
    trainer = Trainer(scene, tiny_cfg("ngp", step_mode="graph", device=device, **kw), path)
    assert trainer.set_step_mode(mode, capture=capture) == mode
    return trainer


def losses(trainer: Trainer, n: int) -> list[float]:
    for _ in range(n):
        trainer.step()
    trainer.flush_stats()
    return [s["loss"] for s in trainer.history]


def graph_keys(graph: Trainer, n: int, part: int) -> list:
    """Step the graphed `graph` n times; part `part` of its graph key after each step (0: the
    batch's shapes, 1: the field's, 2: the calibration's); its stats flushed."""
    keys = []
    for _ in range(n):
        graph.step()
        keys.append(graph.graph._key[part])
    graph.flush_stats()
    return keys


def test_graph_body_takes_the_plain_paths_steps_on_the_cpu(scene, tmp_path):
    plain = make(scene, tmp_path / "plain", "plain", steps=6)
    a = losses(plain, 6)
    graph = make(scene, tmp_path / "graph", "graph", steps=6)
    assert graph.graph is not None and not graph.graph.capture
    assert torch.is_tensor(graph.optimizer.param_groups[0]["lr"])
    b = losses(graph, 6)
    assert_same_losses(a, b)
    for (k, p), q in zip(plain.field.named_parameters(), graph.field.parameters(), strict=True):
        assert_same_tensor(p, q, k)


@pytest.mark.skipif(not CUDA, reason="no CUDA: capture needs it")
@pytest.mark.parametrize("copies", [1, 2])
def test_captured_step_matches_the_device_step(scene, tmp_path, copies):
    """Replayed from one graph, or from two copies in turn (graph_copies), the steps are the
    device path's; a new capacity recaptures every copy."""
    steps = 3 * WARMUP + 6
    device = make(scene, tmp_path / "device", "device", "cuda", steps=steps)
    a = losses(device, steps)
    graph = make(scene, tmp_path / "graph", "graph", "cuda", steps=steps, graph_copies=copies)
    b = losses(graph, steps)
    g = graph.graph
    assert g.failure is None and g.captures >= copies and g.replays >= 3
    assert len(g._graphs) == copies
    assert b == pytest.approx(a, rel=1e-4)
    # a new capacity changes what the graph bakes in: it is captured again
    before = g.captures
    graph.field.sample_capacity.capacity *= 2
    losses(graph, WARMUP + 2)
    assert g.captures == before + copies


def assert_trains_as(scene, tmp_path, base: dict, option: dict) -> None:
    """On CUDA, `option` over NGP_TINY trains as `base` over it does, eagerly (to the GPU
    atomics' order), and replayed from a graph as eagerly."""
    steps = 3 * WARMUP + 6
    a_opts, b_opts = {**NGP_TINY, **base}, {**NGP_TINY, **option}
    runs = [("a", "device", a_opts), ("b", "device", b_opts), ("g", "graph", b_opts)]
    out = []
    # each made just before it runs: a Trainer seeds torch's generator, which the jitter draws from
    for n, mode, o in runs:
        trainer = make(scene, tmp_path / n, mode, "cuda", steps=steps, backend_options=o)
        out.append(losses(trainer, steps))
    a, b, c = out
    graph = trainer.graph
    assert graph.failure is None and graph.replays >= 3
    assert b == pytest.approx(a, rel=2e-2) and c == pytest.approx(b, rel=1e-4)


@pytest.mark.skipif(not CUDA, reason="no CUDA: the fused epilogue is cuBLASLt's")
def test_fused_relu_steps_are_the_plain_mlps_steps_captured_or_not(scene, tmp_path):
    """fused_relu on the GPU (bf16 autocast, the GEMM's ReLU epilogue) trains as the plain
    MLPs do, eagerly and replayed from a graph."""
    assert_trains_as(scene, tmp_path, {"fused_relu": False}, {"fused_relu": True})


@pytest.mark.skipif(not CUDA, reason="no CUDA: bf16 autocast and the block layouts are the GPU's")
@pytest.mark.parametrize(
    "base, option",
    [
        ({"bf16_features": False}, {"bf16_features": True}),
        ({"distortion_layout": "ray"}, {"distortion_layout": "block"}),
    ],
    ids=["bf16", "block"],
)
def test_gpu_options_train_as_without_them_captured_or_not(scene, tmp_path, base, option):
    """bf16_features (the hash grid's and the SH's features in bf16) and the distortion
    loss's block layout change how a step runs, not what it computes."""
    assert_trains_as(scene, tmp_path, base, option)


@pytest.mark.parametrize("device", DEVICES)
def test_graph_step_flags_an_overflowing_sample_buffer(scene, tmp_path, device):
    """A buffer too small for the batch drops whole pixels and says so on the graphed step as
    on the device step; the capacity then grows to what was wanted."""
    trainer = make(scene, tmp_path / "run", "graph", device, steps=20)
    for _ in range(WARMUP + 1):
        trainer.step()
    trainer.flush_stats()
    wanted = trainer.history[-1]["samples_per_ray"] * 2 * 32  # the last batch's samples
    cap = trainer.field.sample_capacity
    # below what a batch wants, with room for some pixels' two rays (rays take their offsets
    # in no fixed order, so a pixel keeps both with about the kept share squared)
    small = cap.capacity = max(16, int(0.6 * wanted))
    stats = [trainer.step() for _ in range(WARMUP + 2)]
    trainer.flush_stats()
    assert all(0 < s["dropped"] < 1 for s in stats)
    assert all(s["samples_per_ray"] * 2 * 32 <= small + 1e-3 for s in stats)
    while trainer.step_count % trainer.field.options.occupancy.update_every:
        trainer.step()
    for _ in range(2 * trainer.field.options.occupancy.update_every):
        trainer.step()  # the want copied at one refresh is applied at the next
    assert cap.capacity > small


def test_graph_mode_falls_back_where_a_step_cannot_be_captured(scene, tmp_path):
    vanilla = Trainer(scene, tiny_cfg("vanilla", step_mode="graph"), tmp_path / "v")
    assert vanilla.step_mode == "device" and vanilla.graph is None
    # plain Adam on the poses decays them at a host-side rate: not capturable
    refined = make(scene, tmp_path / "r", "device", refine_poses=True, refine_optimizer="adam")
    assert refined.set_step_mode("graph") == "device"


def test_graph_mode_survives_a_checkpoint_and_resume(scene, tmp_path):
    trainer = make(scene, tmp_path / "run", "graph", steps=4)
    trainer.run(hooks=[], progress=False)
    trainer.save_checkpoint(finished=True)
    resumed = Trainer(scene, tiny_cfg("ngp", step_mode="device", steps=6), tmp_path / "run", True)
    assert not torch.is_tensor(resumed.optimizer.param_groups[0]["lr"])
    resumed.run(hooks=[], progress=False)
    assert resumed.step_count == 6


def test_graph_body_follows_the_compaction_switch_on_the_cpu(scene, tmp_path):
    """compaction_auto with a share no field reaches (compact_below 0): the run compacts for
    its first updates, then switches compaction off (a new graph key) and the graphed body
    still takes the plain path's steps."""
    opts = {**NGP_TINY, "early_stop_eps": 1e-4, "compaction_auto": True, "compact_below": 0.0}
    kw = dict(steps=40, backend_options=opts)
    plain = make(scene, tmp_path / "plain", "plain", **kw)
    a = losses(plain, 40)
    graph = make(scene, tmp_path / "graph", "graph", **kw)
    b = losses(graph, 40)
    assert_same_losses(a, b)
    for t in (plain, graph):
        assert t.field.compaction.switches == 1 and not t.field.compaction.on
        assert "marched_per_ray" in t.history[0] and "marched_per_ray" not in t.history[-1]


def test_graph_body_applies_a_measured_threshold_ratio_on_the_cpu(scene, tmp_path):
    """estimate_threshold with the ratio counted over the loop learns nothing per step, so the
    step stays graphed (its batch's polarity parts in static buffers) and takes the plain
    path's steps; a learnt ratio keeps the device step."""
    kw = dict(steps=6, estimate_threshold=True)
    plain = make(scene, tmp_path / "plain", "plain", **kw)
    a = losses(plain, 6)
    graph = make(scene, tmp_path / "graph", "graph", **kw)
    assert graph.selfcal.static and graph.step_mode == "graph"
    assert graph.selfcal.thresholds.measured_ratio is not None
    assert_same_losses(a, losses(graph, 6))
    static = graph.graph._static  # what a captured replay reads: this step's parts, not stale
    assert static.parts is not None and static.pix is not None


def test_graph_body_learns_a_threshold_ratio_on_the_cpu(scene, tmp_path):
    """A learnt ratio is graphed too (its lr a device tensor, filled each step): the graphed
    body takes the plain path's steps and learns the same thresholds."""
    kw = dict(steps=6, estimate_threshold=True, threshold_ratio="learn")
    plain = make(scene, tmp_path / "plain", "plain", **kw)
    a = losses(plain, 6)
    graph = make(scene, tmp_path / "graph", "graph", **kw)
    assert not graph.selfcal.static and graph.step_mode == "graph"
    assert torch.is_tensor(graph.selfcal.optimizer.param_groups[0]["lr"])
    assert_same_losses(a, losses(graph, 6))
    want, got = (t.selfcal.thresholds.log_ratio for t in (plain, graph))
    assert_same_tensor(want, got, "log_ratio")
    assert float(got.detach()) != 0.0


def test_graph_body_refines_poses_on_the_cpu(scene, tmp_path):
    """Pose refinement with the row Adam is graphed: its lr and the coarse-to-fine weights are
    device tensors filled before each step, and what they switch (the poses' first step at
    refine_start, every level on at refine_c2f_end, one shared correction until
    refine_shared_until) is in the graph's key. The graphed body takes the plain path's steps
    through every switch, and learns the same poses (through the gate too)."""
    kw = dict(steps=14, refine_poses=True, refine_start=0.2, refine_warmup=0.0)
    kw.update(refine_c2f_start=0.0, refine_c2f_end=0.6, refine_shared_until=0.4)
    kw.update(refine_gate=0.5)  # the gate's state and factor in the graph too (0.5: it opens)
    plain = make(scene, tmp_path / "plain", "plain", **kw)
    a = losses(plain, 14)
    graph = make(scene, tmp_path / "graph", "graph", **kw)
    assert graph.step_mode == "graph"
    keys, weights = [], set()
    for _ in range(14):
        graph.step()
        _, field_key, cal_key = graph.graph._key
        keys.append((field_key[-1], cal_key))  # level weights' use; poses stepping, sharing
        if graph.field.level_weights is not None:  # one tensor, filled in place: a replay reads it
            weights.add(graph.field.level_weights.data_ptr())
    graph.flush_stats()
    assert_same_losses(a, [s["loss"] for s in graph.history])
    # before refine_start, one shared correction, one per pose under c2f, every level on
    assert list(dict.fromkeys(keys)) == [
        ("gradient", (False, True, False)),
        ("gradient", (True, True, False)),
        ("gradient", (True, False, False)),
        (False, (True, False, False)),
    ]
    assert graph.field.level_weights is None and len(weights) == 1
    want, got = (t.selfcal.poses.delta for t in (plain, graph))
    assert_same_tensor(want, got, "delta")
    assert float(got.detach().abs().max()) > 0
    static = graph.graph._static
    assert static.dirs is not None and static.pose_idx is not None


def test_graph_body_takes_the_plain_paths_steps_through_refine_freeze(scene, tmp_path):
    """refine_freeze on the graphed body: the step after the poses settle has another graph
    key (no pose lr, frozen), the same losses as the plain path's through the switch, and
    poses that stop where the plain path's stop."""
    kw = dict(steps=12, refine_poses=True, refine_start=0.0, refine_warmup=0.0)
    kw.update(refine_settle_px=1e3, refine_freeze=True)
    plain = make(scene, tmp_path / "plain", "plain", **kw)
    a = losses(plain, 12)
    graph = make(scene, tmp_path / "graph", "graph", **kw)
    keys = graph_keys(graph, 12, 2)
    assert_same_losses(a, [s["loss"] for s in graph.history])
    assert list(dict.fromkeys(keys)) == [(True, False, False), (False, False, True)]
    assert graph.selfcal.pose_cal.frozen and plain.selfcal.pose_cal.frozen
    want, got = (t.selfcal.poses.delta for t in (plain, graph))
    assert_same_tensor(want, got, "delta")


def test_graph_body_takes_the_plain_paths_steps_through_a_field_restart(scene, tmp_path):
    """refine_restart on the graphed body: the step where the poses settle builds a new
    field, and the graphed step is made again for it (its own buffers and optimiser); the
    losses are the plain path's through the restart and the new fields end alike."""
    kw = dict(steps=12, refine_poses=True, refine_start=0.0, refine_warmup=0.0)
    kw.update(refine_settle_px=1e3, refine_restart=True, refine_restart_deg=0.0, refine_gate=0.0)
    plain = make(scene, tmp_path / "plain", "plain", **kw)
    a = losses(plain, 12)
    graph = make(scene, tmp_path / "graph", "graph", **kw)
    first = graph.graph
    graph.step()
    first.captures, first.replays, first.returns = 3, 40, 1  # what a GPU's would have been
    b = losses(graph, 11)
    assert_same_losses(a, b)
    assert plain.clock == graph.clock and graph.clock.restarts == 1
    assert graph.step_mode == "graph" and graph.graph is not first
    new = graph.graph  # the run's counts carried over (the CPU captures nothing)
    assert (new.captures, new.replays, new.returns) == (3, 40, 1)
    assert graph.graph.field is graph.field
    got = graph.field.state_dict()
    for k, want in plain.field.state_dict().items():
        if isinstance(want, torch.Tensor) and want.is_floating_point():
            assert_same_tensor(want, got[k], k)


@pytest.mark.skipif(not CUDA, reason="no CUDA: capture needs it")
def test_a_field_restart_captures_the_new_fields_step(scene, tmp_path):
    """On CUDA a restart (at the second look) before any capture, then the new field's step
    warmed up, captured and replayed: the steps are the device path's through it (to the
    GPU atomics' order) and nothing gave up capturing."""
    steps = 3 * WARMUP + 6
    kw = dict(steps=steps, refine_poses=True, refine_start=0.0, refine_warmup=0.0)
    kw.update(refine_settle_px=1e3, refine_restart=True, refine_restart_deg=0.0, refine_gate=0.0)
    device = make(scene, tmp_path / "device", "device", "cuda", **kw)
    a = losses(device, steps)
    graph = make(scene, tmp_path / "graph", "graph", "cuda", **kw)
    b = losses(graph, steps)
    g = graph.graph
    assert graph.clock.restarts == 1 and device.clock == graph.clock
    assert g.failure is None and g.captures >= 1 and g.replays >= WARMUP
    assert b == pytest.approx(a, rel=1e-3)


def test_graph_body_takes_the_plain_paths_steps_through_refine_diffuse(scene, tmp_path):
    """refine_diffuse_until on the graphed body: the colour's mask changes in place where
    the hold ends (here at the settle), and the body's steps are the plain path's through it."""
    kw = dict(steps=12, refine_poses=True, refine_start=0.0, refine_warmup=0.0)
    kw.update(refine_settle_px=1e3, refine_diffuse_until=0.5)
    plain = make(scene, tmp_path / "plain", "plain", **kw)
    a = losses(plain, 12)
    graph = make(scene, tmp_path / "graph", "graph", **kw)
    held = []
    for _ in range(12):
        graph.step()
        held.append(graph.selfcal.pose_cal.view_held)
    graph.flush_stats()
    assert_same_losses(a, [s["loss"] for s in graph.history])
    assert held[0] and not held[-1]
    net = graph.field.color_net
    assert bool(net.w_mask[0, net.n_h :].all())  # the SH inputs back on


def test_graph_body_takes_the_plain_paths_steps_through_a_pose_reset(scene, tmp_path):
    """refine_reset_deg on the graphed body: a row turned 5° by hand after the first step is
    put back in place at the next guard, and the body's losses are the plain path's."""
    import math

    kw = dict(steps=12, refine_poses=True, refine_start=0.0, refine_warmup=0.0)
    kw.update(refine_reset_deg=2.0)
    out = []
    for mode in ("plain", "graph"):
        tr = make(scene, tmp_path / mode, mode, **kw)
        tr.step()
        pc = tr.selfcal.pose_cal
        row = int(torch.nonzero(pc.refiner.used)[3])
        with torch.no_grad():
            pc.refiner.delta[row, :3] = torch.tensor([math.radians(5.0), 0.0, 0.0])
        for _ in range(7):
            tr.step()
        tr.flush_stats()
        assert float(pc.resets) == 1.0
        out.append([s["loss"] for s in tr.history])
    assert_same_losses(*out)


def test_graph_body_takes_the_plain_paths_steps_through_a_batch_resize(
    scene, tmp_path, monkeypatch
):
    """samples_per_step resizes the batch where a block starts (here the second, step 17):
    the graphed body takes new static buffers (the batch's shapes are in the key) and the
    plain path's losses through the switch (24 steps: over longer runs the two paths' float
    rounding drifts apart by more than the tolerance, resize or not)."""
    from tests.test_batch_size import small_quantum

    small_quantum(monkeypatch)
    kw = dict(steps=40, rays_per_step=256, windows_per_step=4, samples_per_step=2048)
    plain = make(scene, tmp_path / "plain", "plain", **kw)
    a = losses(plain, 24)
    graph = make(scene, tmp_path / "graph", "graph", **kw)
    shapes = [key[0] for key in graph_keys(graph, 24, 0)]  # rays_o's shape
    assert_same_losses(a, [s["loss"] for s in graph.history])
    assert shapes[:16] == [(512, 3)] * 16 and shapes[16] != (512, 3)  # buffers taken anew
    assert [h["rays"] for h in graph.history] == [h["rays"] for h in plain.history]


@pytest.mark.skipif(not CUDA, reason="no CUDA: capture needs it")
def test_a_failed_capture_leaves_an_eager_step_that_draws_random_numbers(scene, tmp_path):
    """A body that cannot be captured (here: a host sync inside it) gives up capturing with
    one warning and runs eagerly from then on, drawing its jitter from the default generator
    that the failed capture had marked (`graph_step.release_generator`)."""
    trainer = make(scene, tmp_path / "run", "graph", "cuda", steps=20)
    body = trainer.graph.body
    calls = []

    def syncing_body(batch):
        calls.append(1)
        if len(calls) > WARMUP:  # the capture: a sync there invalidates it
            torch.cuda.synchronize()
        return body(batch)

    g = trainer.graph
    trainer.graph = GraphedStep(syncing_body, trainer.field, trainer.device, True, None)
    with pytest.warns(UserWarning, match="CUDA-graph step off"):
        for _ in range(WARMUP + 3):
            trainer.step()
    trainer.flush_stats()
    assert trainer.graph.failure is not None and trainer.graph.captures == 0
    assert all(torch.isfinite(torch.tensor(s["loss"])) for s in trainer.history)
    torch.rand(4, device="cuda")  # the default generator draws again
    del g


def test_graphed_refinement_checkpoints_and_resumes(scene, tmp_path):
    """A graphed run with both options saves its learning rates as device tensors (the row
    Adam's (1,) tensor, the fused Adam's 0-dim one); a resumed run takes them back as floats
    and trains on, graphed again where asked."""
    kw = dict(refine_poses=True, estimate_threshold=True, threshold_ratio="learn")
    trainer = make(scene, tmp_path / "run", "graph", steps=4, **kw)
    assert torch.is_tensor(trainer.selfcal.pose_optimizer.param_groups[0]["lr"])
    trainer.run(hooks=[], progress=False)
    trainer.save_checkpoint(finished=True)
    cfg = tiny_cfg("ngp", step_mode="device", steps=7, **kw)
    resumed = Trainer(scene, cfg, tmp_path / "run", True)
    groups = resumed.selfcal.param_groups()
    assert groups and not any(torch.is_tensor(g["lr"]) for g in groups)
    assert resumed.set_step_mode("graph") == "graph"
    resumed.run(hooks=[], progress=False)
    assert resumed.step_count == 7 and torch.isfinite(resumed.selfcal.poses.delta).all()


def test_capture_copy_needs_a_captured_step(scene, tmp_path):
    """Without a captured graph (a CPU: capture off) there is nothing to copy: one clear
    RuntimeError, and the eager step goes on as before."""
    trainer = make(scene, tmp_path / "run", "graph", steps=4)
    trainer.step()
    assert trainer.graph.graph is None
    with pytest.raises(RuntimeError, match="capture_copy needs a captured step"):
        trainer.graph.capture_copy(trainer.sampler.sample())
    trainer.step()
    trainer.flush_stats()
    assert len(trainer.history) == 2 and all(math.isfinite(s["loss"]) for s in trainer.history)


@pytest.mark.skipif(not CUDA, reason="no CUDA: capture needs it")
def test_capture_copy_is_a_second_graph_of_the_same_step(scene, tmp_path):
    """The copy replays on the step's static inputs and takes a training step of its own (the
    parameters move, the loss stays finite); the trainer's own graph still replays after."""
    trainer = make(scene, tmp_path / "run", "graph", "cuda", steps=40)
    while trainer.graph.graph is None:
        trainer.step()
    a = trainer.graph.graph
    copy = trainer.graph.capture_copy(trainer.sampler.sample())
    assert copy is not a and trainer.graph.graph is a
    before = [p.detach().clone() for p in trainer.field.parameters()]
    copy.replay()
    torch.cuda.synchronize()
    moved = [not torch.equal(b, p) for b, p in zip(before, trainer.field.parameters(), strict=True)]
    assert any(moved)
    trainer.step()
    trainer.flush_stats()
    assert trainer.graph.graph is a and math.isfinite(trainer.history[-1]["loss"])


def test_graph_copies_is_checked_and_changes_nothing_without_capture(scene, tmp_path):
    """graph_copies outside 1..2 is one clear error; on the CPU (nothing captured) two copies
    take the very steps one does."""
    with pytest.raises(InputError, match="graph_copies"):
        tiny_cfg("ngp", graph_copies=3).resolved(scene.config, "cpu")
    one = losses(make(scene, tmp_path / "one", "graph", steps=5), 5)
    two = make(scene, tmp_path / "two", "graph", steps=5, graph_copies=2)  # seeds the RNG anew
    assert two.graph.copies == 2
    assert_same_losses(one, losses(two, 5))


def test_sampler_graph_state_puts_back_the_buffers_a_kept_graph_writes(scene, tmp_path):
    """A key's buffers (the fixed march's, with its key) and the capacity's running maximum
    come back with `set_graph_state` after another capacity made its own, and a march at the
    first capacity then writes into that very buffer (what a kept graph baked in), not a
    new one."""
    trainer = make(scene, tmp_path / "run", "graph", steps=12)
    for _ in range(WARMUP + 1):
        trainer.step()
    field, sampler = trainer.field, trainer.field.sampler
    cap = field.sample_capacity
    first, state = cap.capacity, field.graph_state()
    buf, running = state["fixed"][0], cap.running_max
    assert buf is not None and running is not None and state["max"][0] is running
    cap.capacity = 2 * first
    trainer.step()
    assert sampler._fixed_out is not buf and sampler._fixed_key[1] == 2 * first
    cap.use_running_max(torch.zeros_like(running))  # as a reset leaves it: another tensor
    cap.capacity = first
    field.set_graph_state(state)
    assert sampler._fixed_out is buf and cap.running_max is running
    trainer.step()
    trainer.flush_stats()
    assert sampler._fixed_out is buf  # marched into in place: a replay reads the same
    assert running.item() > 0 and math.isfinite(trainer.history[-1]["loss"])


def test_graph_keys_is_checked_and_changes_nothing_without_capture(scene, tmp_path):
    """graph_keys outside 1..8 is one clear error; on the CPU (nothing captured, nothing
    kept) keeping four keys takes the very steps one does, through a capacity change."""
    with pytest.raises(InputError, match="graph_keys"):
        tiny_cfg("ngp", graph_keys=9).resolved(scene.config, "cpu")

    def run(name, keys):
        trainer = make(scene, tmp_path / name, "graph", steps=8, graph_keys=keys)
        for i in range(8):
            if i == 3:
                trainer.field.sample_capacity.capacity *= 2
            trainer.step()
        trainer.flush_stats()
        assert trainer.graph.keys == keys and not trainer.graph._kept
        return [s["loss"] for s in trainer.history]

    assert_same_losses(run("one", 1), run("four", 4))


@pytest.mark.skipif(not CUDA, reason="no CUDA: capture needs it")
@pytest.mark.parametrize("copies", [1, 2])
def test_a_kept_graph_replays_when_its_capacity_returns(scene, tmp_path, copies):
    """With graph_keys 2 a capacity that goes to another size and back replays the first
    size's graphs (no capture, one return) and the steps stay the device path's; with 1 the
    return captures again."""
    steps = 4 * WARMUP + 8
    device = make(scene, tmp_path / "device", "device", "cuda", steps=steps)
    want = losses(device, steps)
    for keys in (1, 2):
        graph = make(
            scene, tmp_path / f"g{keys}", "graph", "cuda", steps=steps, graph_keys=keys,
            graph_copies=copies,
        )  # fmt: skip
        for _ in range(WARMUP + 2):
            graph.step()
        g, cap = graph.graph, graph.field.sample_capacity
        first, before = cap.capacity, g.captures
        cap.capacity = 2 * first
        for _ in range(WARMUP + 2):
            graph.step()
        assert g.captures == before + copies
        cap.capacity = first
        got = losses(graph, steps - 2 * (WARMUP + 2))
        assert g.failure is None and g.returns == (keys - 1)
        assert g.captures == before + (1 + (keys == 1)) * copies
        assert got == pytest.approx(want, rel=1e-4)


@pytest.mark.skipif(not CUDA, reason="no CUDA: capture needs it")
def test_kept_graphs_let_go_when_the_device_is_short_of_memory(scene, tmp_path):
    """With less than KEEP_FREE_SHARE of the device's memory free (a real allocation fills
    it), a key change keeps nothing: the return to the first capacity captures again, as
    with one key, and the steps go on."""
    graph = make(scene, tmp_path / "g", "graph", "cuda", steps=24, graph_keys=4)
    for _ in range(WARMUP + 2):
        graph.step()
    g, cap = graph.graph, graph.field.sample_capacity
    first, before = cap.capacity, g.captures
    free, total = torch.cuda.mem_get_info()
    ballast = torch.empty(
        int(free - 0.5 * KEEP_FREE_SHARE * total), dtype=torch.uint8, device="cuda"
    )
    try:
        cap.capacity = 2 * first
        for _ in range(WARMUP + 2):
            graph.step()
        assert not g._kept
        cap.capacity = first
        for _ in range(WARMUP + 2):
            graph.step()
    finally:
        del ballast
        torch.cuda.empty_cache()  # back to the driver, for the tests after this one
    graph.flush_stats()
    assert g.failure is None and g.returns == 0 and g.captures == before + 2
    assert math.isfinite(graph.history[-1]["loss"])
