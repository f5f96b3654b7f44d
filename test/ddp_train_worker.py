"""Worker of test_distributed.py, launched by ``torchrun``: a few training steps of
:func:`shape_detector.training.train.train` on a frustum ``.npz``, under whatever process
group torchrun set up (or none). Each rank writes its final parameters to
``OUT/rank<r>.pt``; rank 0's run directory ``OUT/run`` holds the per-step losses.

Usage: ``ddp_train_worker.py FRUSTUMS.npz CONFIG.json OUT``
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import torch


def main(argv: list[str]) -> int:
    from shape_detector.training import distributed as ddp
    from shape_detector.training import frustum_dataset as fds
    from shape_detector.training import train as tr
    from shape_detector.training.config import TrainConfig

    data, cfg_path, out = Path(argv[0]), Path(argv[1]), Path(argv[2])
    env, _ = ddp.setup("cpu")
    cfg = TrainConfig.from_dict(json.loads(cfg_path.read_text()))
    kept: dict[str, torch.nn.Module] = {}
    finish = tr._finish

    def keep_model(run, stopped):  # every rank's network as the run ends (train() keeps it to itself)
        kept["model"] = run.model
        return finish(run, stopped)

    tr._finish = keep_model
    tr.train(cfg, fds.load(data), None, out / "run", seed=7, device="cpu", print_fn=lambda s: None)
    torch.save({k: v.detach().clone() for k, v in kept["model"].state_dict().items()}, out / f"rank{env.rank}.pt")
    if env.active:
        torch.distributed.destroy_process_group()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
