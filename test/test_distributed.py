"""Data-parallel training: two CPU processes under ``torchrun`` (gloo, loopback) end with the
same parameters, and their loss is a single process's on the same global batches."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from child_env import child_env
from shape_detector.model.io import load_checkpoint
from shape_detector.training import distributed as ddp
from shape_detector.training import frustum_dataset as fds

from test_model_scene import make_frame

HERE = Path(__file__).resolve().parent
WORKER = HERE / "ddp_train_worker.py"
#: small network; no BatchNorm (each rank would normalise by its own half of the batch) and no
#: random augmentation or dropout, so that two ranks compute exactly the global batch's terms
CONFIG = {
    "model": {"num_points": 128, "num_object_points": 64, "seg_widths": [16, 16, 32], "seg_head_widths": [16],
              "tnet_widths": [16, 32], "tnet_fc": [16], "box_widths": [16, 32], "box_fc": [32], "shape_fc": [32],
              "shape_widths": [16, 32], "cls_fc": [16], "box_context_widths": [], "box2_widths": [],
              "shape_context_widths": [], "shape_anchors": False, "batchnorm": False, "cls_dropout": 0.0},
    "epochs": 2, "batch_size": 8, "lr": 0.002, "log_every": 1, "num_threads": 1,
    "mirror_prob": 0.0, "scale_min": 1.0, "scale_max": 1.0, "point_jitter": 0.0, "color_jitter": 0.0,
    "onehot_drop_prob": 1.0, "random_gather": False, "shape_box_noise": [0.0, 0.0, 0.0],
}


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _run(cmd: list[str], timeout: float) -> None:
    env = child_env(OMP_NUM_THREADS="1", GLOO_SOCKET_IFNAME="lo")
    for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        env.pop(k, None)
    try:
        p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout, cwd=HERE.parent)
    except subprocess.TimeoutExpired as e:
        pytest.fail(f"{cmd[:4]} did not finish in {timeout} s: {e.stderr!s:.2000}")
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-4000:]


def test_epoch_batches_of_all_ranks_are_the_global_batches():
    one = ddp.epoch_indices(37, 8, ddp.DistEnv(), seed=3, epoch=1)
    ranks = [ddp.epoch_indices(37, 8, ddp.DistEnv(r, 2), seed=3, epoch=1) for r in range(2)]
    assert len(one) == len(ranks[0]) == len(ranks[1]) == 37 // 8
    for k, b in enumerate(one):
        assert sorted(torch.cat([ranks[0][k], ranks[1][k]]).tolist()) == sorted(b.tolist())
    assert [b.tolist() for b in ddp.epoch_indices(37, 8, ddp.DistEnv(), 3, 2)] != [b.tolist() for b in one]
    with pytest.raises(ValueError, match="multiple"):
        ddp.epoch_indices(37, 9, ddp.DistEnv(0, 2), 3, 1)


@pytest.mark.slow
@pytest.mark.skipif(not torch.distributed.is_available(), reason="torch built without torch.distributed")
def test_two_gloo_processes_train_as_one(tmp_path):
    frames = [make_frame(s, 3) for s in range(6)]
    ds = fds.build_frustum_dataset(frames, num_points=128, augment_copies=2, rng_seed=0, negatives_per_frame=0)
    assert fds.num_frustums(ds) >= 24
    data = fds.save(ds, tmp_path / "frustums.npz")
    cfg = tmp_path / "config.json"
    cfg.write_text(json.dumps(CONFIG))
    one, two = tmp_path / "one", tmp_path / "two"
    one.mkdir(), two.mkdir()
    _run([sys.executable, str(WORKER), str(data), str(cfg), str(one)], timeout=120)
    _run([sys.executable, "-m", "torch.distributed.run", "--nnodes", "1", "--nproc_per_node", "2",
          "--master_addr", "127.0.0.1", "--master_port", str(_free_port()),
          str(WORKER), str(data), str(cfg), str(two)], timeout=180)

    r0, r1 = torch.load(two / "rank0.pt"), torch.load(two / "rank1.pt")
    for k in r0:  # DDP's averaged gradients keep the replicas in step
        torch.testing.assert_close(r1[k], r0[k], atol=1e-6, rtol=1e-6, msg=k)
    # the mean of the ranks' losses over their halves is the loss of the whole batch: every term
    # that is a mean over frustums is equal at the first step; the terms that average over GT
    # parts weigh each rank's parts by its own count, so they (and the total) move a little
    h1 = load_checkpoint(one / "run" / "checkpoint.pt")["history"]["steps"]
    h2 = load_checkpoint(two / "run" / "checkpoint.pt")["history"]["steps"]
    assert len(h1) == len(h2) >= 6
    per_part = {"consistency", "part", "volume", "occupancy"}
    for k, v in h1[0].items():
        if k not in per_part and k not in ("epoch", "step", "lr", "total"):
            np.testing.assert_allclose(h2[0][k], v, rtol=1e-5, atol=1e-6, err_msg=k)
    np.testing.assert_allclose(h2[0]["total"], h1[0]["total"], rtol=2e-3)
    # later steps follow from parameters that moved alike
    np.testing.assert_allclose([s["total"] for s in h2], [s["total"] for s in h1], rtol=0.05)
    single = torch.load(one / "rank0.pt")
    drift = max(float((r0[k].float() - single[k].float()).abs().max()) for k in r0 if r0[k].is_floating_point())
    assert drift < 0.05
