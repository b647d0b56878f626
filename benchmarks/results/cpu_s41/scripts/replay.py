"""Replay recorded marcher wants (`wants.py`) through the sample buffers' capacity rule
(`fastenerf.fields.capacity.SampleCapacity`, the class itself) under several settings of its
shrink rule, as the sampler drives it: sized exactly at the first step, a refresh every
`update_every` steps before that step's march, one observed want per step.

    PYTHONPATH=. python benchmarks/results/cpu_s41/scripts/replay.py OUT WANTS.json ...

The quantum is set per scene so that the mean want of the run's second half is QUANTA quanta
(7, 14, 28, 56: the GPU's lattice holds ~7, plant ~27, shiny ~42, the mesh scene ~58 at
32,768 slots). Per scene, quanta and rule: capacity changes (each a CUDA-graph recapture on
the GPU) over the run and in its second half, mean capacity over the second half against the
rule as landed before (patience 1), and steps whose want exceeded the capacity (rays dropped).
Writes OUT/replay.json and OUT/replay.md.
"""

import json
import sys
from pathlib import Path

import torch

from fastenerf.fields.capacity import SampleCapacity

QUANTA = (7, 14, 28, 56)
RULES = {  # name: (min_shrink, shrink_patience)
    "any_shrink": (1, 1),
    "two_quanta": (2, 1),
    "patience2": (2, 2),
    "patience4": (2, 4),
    "patience8": (2, 8),
}


def replay(wants: list[int], every: int, quantum: int, min_shrink: int, patience: int) -> list:
    """The capacity in force at each step."""
    SampleCapacity.min_shrink = min_shrink
    cap = SampleCapacity(quantum=quantum, shrink_patience=patience)
    cap.reset(wants[0])
    caps = []
    for step, w in enumerate(wants):
        if step and step % every == 0:
            cap.refresh()
        caps.append(cap.capacity)
        cap.observe(torch.tensor([w], dtype=torch.int32))
    return caps


def summary(wants: list[int], caps: list[int], quantum: int) -> dict:
    half = len(wants) // 2
    changes = [i for i in range(1, len(caps)) if caps[i] != caps[i - 1]]
    ups = [caps[i] > caps[i - 1] for i in changes]
    return {
        "changes": len(changes),
        "reversals": sum(a != b for a, b in zip(ups, ups[1:], strict=False)),
        "changes_2nd_half": sum(i >= half for i in changes),
        "mean_quanta_2nd_half": sum(caps[half:]) / (len(caps) - half) / quantum,
        "overflow_steps": sum(w > c for w, c in zip(wants, caps, strict=True)),
    }


def main(argv: list[str]) -> int:
    if len(argv) < 2 or Path(argv[0]).exists() or not all(Path(a).is_file() for a in argv[1:]):
        print("replay.py: error: usage: OUT (new) WANTS.json ...", file=sys.stderr)
        return 2
    saved = SampleCapacity.min_shrink
    res, lines = {}, []
    head = "| scene | quanta | " + " | ".join(RULES) + " |"
    lines += [
        "changes over the run (in its second half, back-and-forth turns) · mean capacity in "
        "the second half against "
        "`two_quanta` · steps that overflowed",
        "",
        head,
        "|---|---:|" + "---:|" * len(RULES),
    ]
    try:
        for path in argv[1:]:
            rec = json.loads(Path(path).read_text())
            if not isinstance(rec, dict) or not {"scene", "wants", "update_every"} <= rec.keys():
                raise ValueError(f"{path} is not a wants.py record (scene, wants, update_every)")
            wants, every = rec["wants"], rec["update_every"]
            half_mean = sum(wants[len(wants) // 2 :]) / (len(wants) - len(wants) // 2)
            for quanta in QUANTA:
                q = max(1, round(half_mean / quanta))
                row = {}
                for name, (m, k) in RULES.items():
                    row[name] = summary(wants, replay(wants, every, q, m, k), q)
                base = row["two_quanta"]["mean_quanta_2nd_half"]
                res[f"{rec['scene']}/{quanta}"] = {"quantum": q, **row}
                cells = [
                    f"{r['changes']} ({r['changes_2nd_half']}, {r['reversals']}) · "
                    f"{r['mean_quanta_2nd_half'] / base - 1:+.1%} · {r['overflow_steps']}"
                    for r in row.values()
                ]
                lines.append(f"| {rec['scene']} | {quanta} | " + " | ".join(cells) + " |")
    except (OSError, KeyError, ValueError) as e:
        print(f"replay.py: error: {e}", file=sys.stderr)
        return 2
    finally:
        SampleCapacity.min_shrink = saved
    out = Path(argv[0])
    out.mkdir(parents=True)
    (out / "replay.json").write_text(json.dumps(res, indent=1))
    (out / "replay.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
