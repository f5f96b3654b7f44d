"""Training loop of FrustumShapeNet (end-to-end multi-task, task flags, frozen parts).

:func:`train` takes frustum datasets (see :mod:`.frustum_dataset`), trains with Adam,
cosine (or step) LR decay and Frustum-PointNets-style BatchNorm momentum decay, validates
every epoch and writes to ``out_dir``::

    checkpoint.pt      resumable (model, optimiser, epoch, step, history, configs)
    weights.pt         last epoch, inference only (float16, temperature-calibrated)
    best.pt            best validation epoch, inference only (calibrated)
    log.csv, log.json  one row per epoch (train losses, val metrics, lr, time)
    loss_curve.png     train losses per logged step + validation metrics per epoch
    val_metrics.json   final validation metrics of best.pt and weights.pt + calibration

What a finished run computes depends only on its config, data, init and seed: the random
streams are re-seeded from (seed, epoch, rank) every epoch, so a resumed run continues
exactly, and a time budget (``max_minutes``) only stops a run early (resumable), never
re-plans it. Under ``torchrun`` the same loop runs data-parallel (see :mod:`.distributed`).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..digests import sha256_file
from ..model.io import default_weights_path, load_checkpoint, load_weights, model_from_state, save_checkpoint, save_weights
from ..model.losses import ALL_TASKS, LossWeights, compute_losses, distillation_losses, parse_tasks
from ..model.network import FrustumShapeNet
from ..model.pointnet import set_bn_momentum
from . import distributed as ddp
from . import frustum_dataset as fds
from .calibration import calibrate
from .config import TrainConfig
from .init_from import class_path_frozen, freeze, init_shape_anchors, load_init
from .logs import fmt_eta, write_logs
from .provenance import make_provenance, utc_now
from .tensor_data import TensorData, shape_box_from_gt
from .validate import evaluate

_SUMMARY_KEYS = ("seg_acc", "box_iou", "box_acc25", "box_acc50", "box_iou_agnostic", "heading_acc_30deg", "shape_iou",
                 "shape_iou_gtbox", "shape_surface_dist", "shape_surface_dist_gtbox", "cls_acc_agnostic",
                 "cls_ece_agnostic")


def lr_at(cfg: TrainConfig, step: int, total_steps: int, steps_per_epoch: int) -> float:
    """Learning rate at optimiser step ``step`` of ``total_steps``."""
    if cfg.lr_schedule == "step":
        return cfg.lr * cfg.lr_gamma ** int(step / max(1, steps_per_epoch) // max(1, cfg.lr_step_epochs))
    p = min(1.0, step / max(1, total_steps))
    return cfg.lr * (cfg.lr_min_frac + (1 - cfg.lr_min_frac) * 0.5 * (1 + math.cos(math.pi * p)))


def _l_at(cfg: TrainConfig, progress: float) -> int:
    sched = list(cfg.coverage_l_schedule) or [1]
    return int(sched[min(int(progress * len(sched)), len(sched) - 1)])


def _bn_momentum(cfg: TrainConfig, samples: int) -> float:
    return max(cfg.bn_momentum_min, cfg.bn_momentum_init * 0.5 ** (samples / max(1, cfg.bn_decay_samples)))


def _stream_seed(seed: int, epoch: int, rank: int) -> int:
    return (int(seed) * 1_000_003 + int(epoch) * 7919 + int(rank) * 104_729) % (2**63 - 1)


@dataclass
class _Run:
    """The state of one training run."""

    cfg: TrainConfig
    tasks: frozenset
    model: FrustumShapeNet
    net: torch.nn.Module
    opt: torch.optim.Optimizer
    frozen: list
    tdata: TensorData
    vdata: TensorData | None
    env: ddp.DistEnv
    out_dir: Path
    seed: int
    say: Callable[[str], None]
    meta: dict[str, Any]
    provenance: dict[str, Any]
    history: dict[str, Any] = field(default_factory=lambda: {"epochs": [], "steps": []})
    epoch: int = 0
    step: int = 0
    best: float = -float("inf")
    elapsed_before: float = 0.0
    gen: torch.Generator = field(default_factory=torch.Generator)
    teacher: FrustumShapeNet | None = None

    @property
    def steps_per_epoch(self) -> int:
        return max(1, self.tdata.n // int(self.cfg.batch_size))


def _build_model(cfg: TrainConfig, train_ds: dict[str, np.ndarray], seed: int, device: torch.device,
                 init_weights: str | Path | None, resuming: bool, say: Callable[[str], None]):
    """The network to train (fresh, or from ``init_weights``), its frozen leaves and the tasks
    its weights will carry."""
    torch.manual_seed(seed)
    np.random.seed(seed % (2**32))
    model = FrustumShapeNet(cfg.model_config()).to(device)
    anchors_ready = resuming
    weight_tasks = set(parse_tasks(cfg.tasks))
    if init_weights is not None:
        init_model, init_meta = load_weights(init_weights, device)
        # a fine-tune's weights also carry the heads its init trained
        weight_tasks |= set(init_meta.get("tasks") or ALL_TASKS)
        if not resuming:
            anchors_ready = load_init(model, init_model, cfg.reinit)
            say(f"initialised from {init_weights}" + (f" except {cfg.reinit} (fresh)" if cfg.reinit else ""))
    if model.shape_anchor is not None and not anchors_ready:
        found = init_shape_anchors(model, train_ds, seed)
        say(f"shape anchors: class templates of {int(found.sum())} classes; shape head output re-initialised")
    frozen = freeze(model, cfg.trainable)
    if frozen:
        say(f"training only {cfg.trainable}: {len(frozen)} modules frozen")
    return model, frozen, sorted(weight_tasks)


def load_teacher(cfg: TrainConfig, student: FrustumShapeNet, device: torch.device) -> tuple[FrustumShapeNet, str]:
    """The frozen network of ``cfg.teacher`` ("default": the packaged weights) and its path;
    ValueError when its heads do not match the student's (classes, heading bins, size
    clusters)."""
    path = default_weights_path() if cfg.teacher == "default" else Path(str(cfg.teacher))
    teacher, _ = load_weights(path, device)
    for key in ("num_classes", "num_heading_bins", "num_size_clusters"):
        if getattr(teacher.config, key) != getattr(student.config, key):
            raise ValueError(f"teacher {path}: {key} {getattr(teacher.config, key)} differs from the trained "
                             f"network's {getattr(student.config, key)}")
    teacher.eval()
    for p in teacher.parameters():
        p.requires_grad_(False)
    return teacher, str(path)


def _setup(cfg: TrainConfig, train_ds, val_ds, out_dir: Path, seed: int, device: torch.device, resume: bool,
           say: Callable[[str], None], extra_meta, init_weights, provenance) -> _Run:
    env = ddp.current()
    if device.type == "cpu" and cfg.num_threads:
        torch.set_num_threads(int(cfg.num_threads))
    ck_path = out_dir / "checkpoint.pt"
    resuming = resume and ck_path.is_file()
    model, frozen, weight_tasks = _build_model(cfg, train_ds, seed, device, init_weights, resuming, say)
    ck = load_checkpoint(ck_path) if resuming else None
    if ck is not None:
        model.load_state_dict(model_from_state(ck, device).state_dict())
    net = ddp.wrap(model, env, device)
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=cfg.lr,
                           weight_decay=cfg.weight_decay)
    nc = model.config.num_classes
    tdata = TensorData(train_ds, device, nc)
    vdata = TensorData(val_ds, device, nc) if val_ds is not None and fds.num_frustums(val_ds) else None
    meta = {"tasks": weight_tasks, "seed": seed, "train_config": cfg.to_dict(), "model_config": model.config.to_dict(),
            "train_frustums": tdata.n, "val_frustums": vdata.n if vdata else 0, "device": str(device),
            "world_size": env.world_size, **(extra_meta or {})}
    prov = dict(provenance) if provenance is not None else make_provenance("adhoc", world_size=env.world_size)
    prov["world_size"] = env.world_size
    run = _Run(cfg, parse_tasks(cfg.tasks), model, net, opt, frozen, tdata, vdata, env, out_dir, seed, say, meta, prov)
    # the teacher costs a forward a step: load it only where a distillation term can move a weight
    distilling = any(v > 0 for k, v in LossWeights.from_dict(cfg.loss_weights).to_dict().items()
                     if k.startswith("distill_"))
    reachable = not cfg.trainable or not model.part_names(cfg.trainable) <= FrustumShapeNet.SHAPE_ONLY
    if cfg.teacher and not (distilling and reachable):
        say("teacher not used: no distillation weight is set, or only the shape branch trains "
            "(no distilled output depends on it)")
    elif cfg.teacher:
        run.teacher, teacher_path = load_teacher(cfg, model, device)
        meta["teacher"] = {"path": teacher_path, "sha256": sha256_file(teacher_path)}
        say(f"distilling from {teacher_path} (temperature {cfg.distill_temperature})")
    if ck is not None:
        opt.load_state_dict(ck["optimizer"])
        run.epoch, run.step = int(ck["epoch"]), int(ck["step"])
        run.history = ck.get("history", run.history)
        run.best = float(ck.get("best", run.best))
        run.elapsed_before = float(ck.get("elapsed_s", 0.0))
        say(f"resumed from {ck_path} at epoch {run.epoch} (step {run.step})")
    return run


def _step(run: _Run, idx: torch.Tensor, lr: float, l_near: int) -> dict[str, float]:
    """One optimiser step on this rank's batch ``idx``; returns its loss terms."""
    cfg, model = run.cfg, run.model
    for grp in run.opt.param_groups:
        grp["lr"] = lr
    set_bn_momentum(model, _bn_momentum(cfg, run.step * int(cfg.batch_size)))
    b = run.tdata.batch(idx, cfg, augment=True, generator=run.gen, one_hot_mode="train")
    gt_frame = "shape" in run.tasks and cfg.shape_frame == "gt_box"
    sbox = shape_box_from_gt(b, cfg.shape_box_noise, run.gen) if gt_frame else None
    out = run.net(b["points"], b["one_hot"], random_gather=bool(cfg.random_gather), shape_box=sbox)
    weights = LossWeights.from_dict(cfg.loss_weights)
    L = compute_losses(out, b, model.mean_sizes, run.tasks, weights, l_near,
                       cfg.consistency_per_face, model.config.primitive_min_size_frac, cfg.shape_frame)
    if run.teacher is not None:
        with torch.no_grad():
            t_out = run.teacher(b["points"], b["one_hot"], random_gather=False, with_shape=False)
        for k, v in distillation_losses(out, t_out, b, weights, cfg.distill_temperature).items():
            L[k] = v
            L["total"] = L["total"] + v
    run.opt.zero_grad(set_to_none=True)
    L["total"].backward()
    if cfg.grad_clip > 0:
        torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
    run.opt.step()
    run.step += 1
    return {k: float(v.detach()) for k, v in L.items()}


def _log_progress(run: _Run, it: int, avg: dict[str, float], lr: float, l_near: int, t_ep: float) -> None:
    spe = run.steps_per_epoch
    run.history["steps"].append({"step": run.step, "epoch": run.epoch + (it + 1) / spe, "lr": lr,
                                 **{k: round(v, 6) for k, v in avg.items() if not k.startswith("stat_")}})
    done = (it + 1) / spe
    spent = time.time() - t_ep
    eta = spent / done * (1 - done) + spent / done * (run.cfg.epochs - run.epoch - 1)
    bar = "#" * int(done * 20) + "." * (20 - int(done * 20))
    parts = " ".join(f"{k} {v:.3f}" for k, v in avg.items() if k != "total" and not k.startswith("stat_"))
    st = " ".join(f"{k[5:]} {v:.3f}" for k, v in avg.items() if k.startswith("stat_"))
    run.say(f"ep {run.epoch + 1}/{run.cfg.epochs} [{bar}] {it + 1}/{spe} loss {avg['total']:.3f} ({parts}) [{st}] "
            f"lr {lr:.2e} l={l_near} {spent / (it + 1):.2f}s/it eta {fmt_eta(eta)}")


def _train_epoch(run: _Run, out_of_time: Callable[[], bool]) -> tuple[bool, dict[str, float], float]:
    """One epoch; returns (completed, mean train losses, last lr). Not completed: the time
    budget ran out mid-epoch (the checkpoint keeps the last full epoch)."""
    cfg, env = run.cfg, run.env
    rs = _stream_seed(run.seed, run.epoch, env.rank)
    torch.manual_seed(rs)
    run.gen.manual_seed(rs + 1)
    run.net.train()
    for m in run.frozen:
        m.eval()  # frozen BatchNorm keeps its statistics
    t_ep = time.time()
    batches = ddp.epoch_indices(run.tdata.n, int(cfg.batch_size), env, run.seed, run.epoch)
    total_steps = cfg.epochs * run.steps_per_epoch
    run_sums: dict[str, float] = {}
    ep_sums: dict[str, float] = {}
    run_n, lr = 0, cfg.lr
    for it, idx in enumerate(batches):
        lr = lr_at(cfg, run.step, total_steps, run.steps_per_epoch)
        l_near = _l_at(cfg, run.step / max(1, total_steps))
        for k, v in _step(run, idx, lr, l_near).items():
            run_sums[k] = run_sums.get(k, 0.0) + v
            ep_sums[k] = ep_sums.get(k, 0.0) + v
        run_n += 1
        last = it == len(batches) - 1
        if run_n >= cfg.log_every or last:
            avg = ddp.mean_scalars(env, {k: v / run_n for k, v in run_sums.items()})
            if env.is_main:
                _log_progress(run, it, avg, lr, l_near, t_ep)
            run_sums, run_n = {}, 0
        if not last and ddp.broadcast_flag(env, out_of_time()):
            return False, {}, lr
    means = ddp.mean_scalars(env, {k: v / len(batches) for k, v in ep_sums.items()})
    return True, means, lr


def _end_epoch(run: _Run, train_means: dict[str, float], lr: float, t_train: float, elapsed: float) -> None:
    """Validate, keep the best, write checkpoint, weights and logs (rank 0 only)."""
    run.epoch += 1
    row: dict[str, Any] = {"epoch": run.epoch, "lr": lr, "train_s": round(t_train, 2)}
    row.update({"train_" + k: v for k, v in train_means.items()})
    t_v = time.time()
    if run.vdata is not None:
        row.update(evaluate(run.model, run.vdata, run.cfg, run.tasks, run.cfg.val_max_frustums, seed=run.seed)[0])
    row["val_s"] = round(time.time() - t_v, 2)
    row["elapsed_s"] = round(elapsed, 1)
    run.history["epochs"].append(row)
    sel = row.get("select", -row.get("train_total", 0.0))
    is_best = sel > run.best
    meta = {**run.meta, "epoch": run.epoch, "val": row}
    if is_best:
        run.best = sel
        save_weights(run.model, run.out_dir / "best.pt", meta=meta, provenance=_prov(run, row))
    save_checkpoint(run.out_dir / "checkpoint.pt", run.model, optimizer=run.opt.state_dict(), epoch=run.epoch,
                    step=run.step, history=run.history, best=run.best, elapsed_s=elapsed,
                    train_config=run.cfg.to_dict(), meta=run.meta)
    save_weights(run.model, run.out_dir / "weights.pt", meta=meta, provenance=_prov(run, row))
    write_logs(run.out_dir, run.history, run.meta)
    summ = " ".join(f"{k} {row[k]:.3f}" for k in _SUMMARY_KEYS if k in row)
    run.say(f"epoch {run.epoch}: train {t_train:.1f}s val {row['val_s']:.1f}s  {summ}{'  *best*' if is_best else ''}")


def _prov(run: _Run, metrics: dict[str, Any]) -> dict[str, Any]:
    return {**run.provenance, "metrics": {k: v for k, v in metrics.items() if isinstance(v, (int, float))},
            "created_utc": utc_now()}


def _finish(run: _Run, stopped_early: bool) -> dict[str, Any]:
    """Calibrate the class head of weights.pt and best.pt on the validation set (rank 0)."""
    final: dict[str, Any] = {"tasks": sorted(run.tasks), "epochs_done": run.epoch, "stopped_early": stopped_early}
    if run.vdata is None or run.epoch == 0 or stopped_early or not run.env.is_main:
        return final
    device = run.tdata.device
    for name in ("weights.pt", "best.pt"):
        p = run.out_dir / name
        if not p.is_file():
            continue
        m, wmeta = load_weights(p, device)
        prov = wmeta.pop("provenance", {})
        vm, raw = evaluate(m, run.vdata, run.cfg, run.tasks, run.cfg.val_max_frustums, seed=run.seed)
        # without the class task, or when nothing the class logits depend on was trained,
        # the class head computes what it did: keep its temperature
        recal = "cls" in run.tasks and not class_path_frozen(run.cfg.trainable)
        cal = calibrate(raw) if recal else {"temperature": float(m.cls_temperature), "kept": True}
        m.cls_temperature.fill_(float(cal["temperature"]))
        wmeta["calibration"] = cal
        wmeta["val"] = vm
        prov["metrics"] = {k: v for k, v in vm.items() if isinstance(v, (int, float))}
        save_weights(m, p, meta=wmeta, provenance=prov)
        final[name] = {"epoch": wmeta.get("epoch"), "metrics": vm, "calibration": cal}
    (run.out_dir / "val_metrics.json").write_text(json.dumps(final, indent=1))
    cal = final.get("best.pt", {}).get("calibration", {})
    if "after_agnostic" in cal:
        run.say(f"calibration (best.pt): T = {cal['temperature']:.3f}; agnostic ECE "
                f"{cal['before_agnostic']['ece']:.3f} -> {cal['after_agnostic']['ece']:.3f}, "
                f"given ECE {cal['before_given']['ece']:.3f} -> {cal['after_given']['ece']:.3f}")
    return final


def train(
    cfg: TrainConfig,
    train_ds: dict[str, np.ndarray],
    val_ds: dict[str, np.ndarray] | None,
    out_dir: str | Path,
    seed: int = 0,
    device: str | torch.device = "cpu",
    resume: bool = False,
    max_minutes: float | None = None,
    print_fn: Callable[[str], None] = print,
    extra_meta: dict[str, Any] | None = None,
    stop_after_epochs: int | None = None,
    init_weights: str | Path | None = None,
    provenance: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Train (or resume) and return the final validation metrics (see module docstring).

    ``stop_after_epochs`` ends this call after that many epochs in total and ``max_minutes``
    after that much wall-clock time (the LR schedule is always planned for ``cfg.epochs``);
    ``resume=True`` continues from the checkpoint. ``init_weights`` starts from a trained
    model (ignored when resuming). ``provenance`` is the block written into every weights
    file (its metrics and time are filled in at each save).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    device = torch.device(device)
    env = ddp.current()
    say = print_fn if env.is_main else (lambda s: None)
    run = _setup(cfg, train_ds, val_ds, out_dir, seed, device, resume, say, extra_meta, init_weights, provenance)
    say(f"training {run.model.num_parameters() / 1e6:.2f} M params on {device} x {env.world_size} process(es) "
        f"({torch.get_num_threads()} threads): {run.tdata.n} train / {run.vdata.n if run.vdata else 0} val "
        f"frustums, {run.steps_per_epoch} steps/epoch x {cfg.epochs} epochs, tasks {','.join(sorted(run.tasks))}")
    t_start = time.time()
    budget_s = max_minutes * 60.0 if max_minutes else None

    def out_of_time() -> bool:
        return budget_s is not None and time.time() - t_start > budget_s

    stopped = False
    while run.epoch < cfg.epochs and (stop_after_epochs is None or run.epoch < stop_after_epochs):
        t_ep = time.time()
        done, means, lr = _train_epoch(run, out_of_time)
        if not done:
            stopped = True
            say("time budget exceeded mid-epoch; stopping (resume continues from the last full epoch)")
            break
        if env.is_main:
            _end_epoch(run, means, lr, time.time() - t_ep, run.elapsed_before + time.time() - t_start)
        else:
            run.epoch += 1
        ddp.barrier(env)
        if run.epoch < cfg.epochs and ddp.broadcast_flag(env, out_of_time()):
            stopped = True
            say("time budget exceeded; stopping (resume continues from here)")
            break
    final = _finish(run, stopped)
    if env.is_main:
        write_logs(out_dir, run.history, run.meta)
    ddp.barrier(env)
    return final
