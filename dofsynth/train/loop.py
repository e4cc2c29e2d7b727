"""The training loop, in the manner of nanoGPT's train.py: one function, top to bottom. It
trains the DoF networks (DeepLensNet) or, with [train] task = "depth", the depth network
(dofsynth.train.depth); `forward_loss` and `evaluate` are the only places they differ.

    dofsynth train recipes/train-tiny.toml --data OUT --run RUN             # CPU or one GPU
    torchrun --nproc_per_node 8 -m dofsynth -- train CONFIG --data OUT --run RUN --device cuda

What happens: set up (distributed or not), resolve the config against the data and write it to
RUN/config.toml, build the model and AdamW, resume from RUN/ckpt.pt if it exists, then step:
batch -> forward (autocast on CUDA) -> loss D(L) + beta D(H) (dofsynth.train.loss) -> backward
-> clip -> step -> moving average of the weights ([train] ema). Every log_interval steps a row
goes to RUN/log.csv (and TensorBoard when installed); every eval_interval steps the validation
share of the train split ([data] val_share, never the test split) is evaluated, all of it, with
the averaged weights, and the best so far go to RUN/best.pt (what `render --model` and `eval`
use); every checkpoint_interval steps, and at the end, RUN/ckpt.pt is written. Under torchrun every rank trains on its share of the shards and
DistributedDataParallel averages the gradients; only rank 0 writes files.

Resume: running the same command again continues from the checkpoint's step, optimizer state,
RNG states and data position (epoch, batch); on one process the continued run is identical to
an uninterrupted one. `--steps N` (stop_at) stops early without changing the learning-rate
schedule, which always runs to train.max_steps. A config other than the stored one is refused.
"""
from __future__ import annotations

import csv
import gc
import math
import os
import sys
import time
from contextlib import nullcontext
from pathlib import Path

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel

from dofsynth import progress
from dofsynth.files import atomic_write_bytes, canonical_json, csv_text
from dofsynth.rng import stream_int
from dofsynth.train import checkpoint
from dofsynth.train.config import Config, from_dict, to_toml
from dofsynth.train.data import from_workers, full_res_signed, make_loader, resolve
from dofsynth.train.depth import depth_loss, depth_mae, load_backbone
from dofsynth.train.depth_data import make_depth_loader
from dofsynth.train.estimates import ESTIMATES, write_estimates
from dofsynth.train.loss import deeplens_loss

LOG_FIELDS = ["step", "epoch", "lr", "loss", "loss_low", "loss_high", "loss_depth", "loss_seg",
              "val_loss", "val_psnr", "val_mae", "samples_per_s", "elapsed_s"]


def learning_rate(step: int, cfg: Config) -> float:
    """Linear warm-up to train.lr, then cosine decay to train.min_lr at train.max_steps."""
    t = cfg.train
    if step < t.warmup_steps:
        return t.lr * (step + 1) / t.warmup_steps
    progress = min(1.0, (step - t.warmup_steps) / max(1, t.max_steps - t.warmup_steps))
    return t.min_lr + 0.5 * (1.0 + math.cos(math.pi * progress)) * (t.lr - t.min_lr)


def batch_stream(dataset, loader, epoch: int, skip: int):
    """Endless (epoch, batch index, batch) triples, starting `skip` batches into `epoch` (the
    dataset skips them without decoding)."""
    while True:
        dataset.set_epoch(epoch, skip_batches=skip)
        n = 0
        for i, batch in enumerate(from_workers(loader), start=skip):
            n += 1
            yield epoch, i, batch
        if n == 0 and skip == 0:
            raise ValueError("the training split yielded no batch (no samples for this process)")
        epoch, skip = epoch + 1, 0


def prepare_log(path: Path, step: int) -> None:
    """RUN/log.csv with its header and only the rows up to `step` (a killed run may have logged
    past its last checkpoint, or died before writing a row or even its header)."""
    rows = []
    if path.is_file():
        with open(path, newline="") as fh:
            reader = csv.DictReader(fh)
            rows = list(reader) if reader.fieldnames and "step" in reader.fieldnames else []
        keep = [r for r in rows if r.get("step", "").isdigit() and int(r["step"]) <= step]
        if keep == rows and rows:
            return
        rows = keep
    atomic_write_bytes(path, csv_text(LOG_FIELDS, rows).encode())


def check_finite(loss: torch.Tensor, batch: dict, step: int, last_saved: int | None) -> None:
    """Stop at a non-finite loss, naming the samples of the batch (the one with NaN or inf in
    its inputs, if any); nothing of this step is applied or saved."""
    if bool(torch.isfinite(loss).item()):
        return
    where = [f"{k} ({s})" if s else k for k, s in zip(batch["key"], batch.get("shard", [""] * len(batch["key"])))]
    inputs = [v for v in batch.values() if torch.is_tensor(v) and v.is_floating_point() and v.ndim == 4]
    bad = [w for i, w in enumerate(where) if any(not torch.isfinite(v[i]).all() for v in inputs)]
    kept = f"; the checkpoint of step {last_saved} is kept" if last_saved else ""
    what = f"NaN or inf in the inputs of {', '.join(bad)}" if bad else f"batch of {', '.join(where)}"
    raise ValueError(f"step {step + 1}: the loss is {loss.item()} ({what}){kept}")


def to_device(batch: dict, device) -> dict:
    return {k: v.to(device, non_blocking=True) if torch.is_tensor(v) else v for k, v in batch.items()}


def psnr_each(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """PSNR (dB) of each image of a batch in [0, 1] (B, C, H, W) -> (B,)."""
    mse = ((x.float().clamp(0, 1) - y.float()) ** 2).flatten(1).mean(1)
    return 10 * torch.log10(1.0 / mse.clamp_min(1e-10))


def forward_loss(model, b: dict, cfg: Config):
    """(loss, {log field: term}, per-sample score) of one batch: for the DoF networks J(L) +
    beta J(H) and the PSNR of H (dB); for the depth network J_d and the MAE of the normalized
    disparity."""
    if cfg.train.task == "depth":
        depth, seg = model(b["image"])
        loss, j_d, j_s = depth_loss(depth, seg, b, cfg.depth.gamma)
        return loss, {"loss_depth": j_d, "loss_seg": j_s}, depth_mae(depth, b)[b["has_depth"] > 0]
    low, high = model(b["image"], b["signed_lo"], cfg.data.levels, b["image_lo"], **full_res_signed(b, cfg))
    loss, j_low, j_high = deeplens_loss(low, high, b["target_lo"], b["target"],
                                        cfg.loss.alpha, cfg.loss.beta, cfg.loss.eps, cfg.loss.l1, cfg.loss.kind,
                                        cfg.loss.teacher, b.get("teacher_lo"), cfg.loss.ssim)
    return loss, {"loss_low": j_low, "loss_high": j_high}, psnr_each(high, b["target"])


@torch.no_grad()
def evaluate(model, loader, cfg: Config, device, autocast) -> dict:
    """Loss (per batch) and the score of `forward_loss` (per sample: val_psnr, or val_mae for
    the depth network), averaged over the whole validation share (or its first
    train.eval_batches batches when that is > 0), all ranks together."""
    model.eval()
    totals = torch.zeros(4, device=device, dtype=torch.float64)  # loss sum, batches, score sum, samples
    for i, batch in enumerate(from_workers(loader)):
        if cfg.train.eval_batches and i >= cfg.train.eval_batches:
            break
        b = to_device(batch, device)
        with autocast:
            loss, _, score = forward_loss(model, b, cfg)
        totals += torch.stack([loss.double(), torch.ones((), device=device, dtype=torch.float64),
                               score.double().sum(), torch.tensor(float(score.numel()), device=device, dtype=torch.float64)])
    if dist.is_initialized():
        dist.all_reduce(totals)
    model.train()
    name = "val_mae" if cfg.train.task == "depth" else "val_psnr"
    return {"val_loss": totals[0].item() / max(1.0, totals[1].item()), name: totals[2].item() / max(1.0, totals[3].item())}


def train(cfg: Config, data_dir: str | Path, run_dir: str | Path, *, device: str = "auto",
          stop_at: int | None = None, out=None) -> dict:
    """Train (or continue training) the config's network; returns {"step", "loss", "val_loss", ...}.

    stop_at: stop after this step (at most train.max_steps) this time; the learning-rate
    schedule still runs to train.max_steps, so stopping and resuming changes nothing.
    """
    # -- processes and device ------------------------------------------------------------------
    ddp = int(os.environ.get("WORLD_SIZE", "1")) > 1
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError("--device cuda: no CUDA device is available")
    if ddp:
        dist.init_process_group(backend="nccl" if device.startswith("cuda") else "gloo")
        rank, world = dist.get_rank(), dist.get_world_size()
        if device.startswith("cuda"):
            device = f"cuda:{int(os.environ['LOCAL_RANK'])}"
            torch.cuda.set_device(device)
    else:
        rank, world = 0, 1
    master = rank == 0
    cuda = device.startswith("cuda")
    out = out or sys.stdout
    say = (lambda msg: print(msg, file=out, flush=True)) if master and not progress.quiet() else (lambda msg: None)

    # -- config, run folder, resume ------------------------------------------------------------
    run_dir = Path(run_dir)
    depth_task = cfg.train.task == "depth"
    cfg = cfg if depth_task else resolve(cfg, data_dir)
    ckpt_path = run_dir / checkpoint.CHECKPOINT
    state = checkpoint.load(ckpt_path) if ckpt_path.is_file() else None  # on the CPU: RNG states stay CPU tensors
    if state is not None:
        stored = from_dict(state["config"], str(ckpt_path))
        if stored != cfg:
            raise ValueError(f"{run_dir}: was trained with another config (see {run_dir / 'config.toml'}); "
                             "use a new --run folder or the same config")
    if master:
        run_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(run_dir / "config.toml", to_toml(cfg).encode())
        env = {"torch": torch.__version__, "python": sys.version.split()[0], "device": device,
               "world_size": world, "cuda": torch.cuda.get_device_name(device) if cuda else None}
        atomic_write_bytes(run_dir / "env.json", canonical_json(env, indent=2))

    # -- model, optimizer, precision -----------------------------------------------------------
    t = cfg.train
    torch.manual_seed(stream_int(t.seed, "init"))  # the same initial weights on every rank
    model = checkpoint.build_model(cfg)
    if depth_task and cfg.depth.weights and state is None:
        say(f"backbone: {load_backbone(model, cfg.depth.weights)} tensors from {cfg.depth.weights}")
    model = model.to(device)
    optimizer = torch.optim.AdamW(model.parameters(), lr=t.lr, betas=tuple(t.betas),
                                  weight_decay=t.weight_decay)
    ema = checkpoint.Ema(model, t.ema) if t.ema > 0 else None
    step, epoch, batch_index, best = 0, 0, 0, None
    if state is not None:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        if ema is not None:
            ema.module.load_state_dict(state.get("ema") or state["model"])
        step, epoch, batch_index, best = state["step"], state["epoch"], state["batch"] + 1, state.get("best_score")
        checkpoint.set_rng_states(state["rng"])
        say(f"resuming {run_dir} at step {step}")
    last_saved = step if state is not None else None
    end = t.max_steps if stop_at is None else min(int(stop_at), t.max_steps)
    if step >= end:
        say(f"{run_dir}: already trained to step {step} (stop at {end}, max_steps {t.max_steps})")
        if ddp:
            dist.destroy_process_group()
        return {"step": step, "loss": None}
    dtype = {"bfloat16": torch.bfloat16, "float16": torch.float16, "float32": torch.float32}[t.dtype]
    amp = cuda and dtype != torch.float32
    autocast = torch.autocast("cuda", dtype=dtype) if amp else nullcontext()
    scaler = torch.amp.GradScaler("cuda", enabled=amp and dtype == torch.float16)
    if t.compile and cuda:
        model = torch.compile(model)
    if ddp:
        model = DistributedDataParallel(model, device_ids=[torch.device(device).index] if cuda else None)

    # -- data ------------------------------------------------------------------------------------
    estimates = None
    if not depth_task and cfg.augment.predicted_prob > 0:  # the depth run's estimates, made once per run
        if master:
            say(f"depth estimates of {cfg.augment.predicted_run} -> {run_dir / ESTIMATES}")
            write_estimates(cfg, data_dir, run_dir, device)
        if ddp:
            dist.barrier()
        estimates = run_dir / ESTIMATES
    loader_of = make_depth_loader if depth_task else (
        lambda d, *a, **k: make_loader(d, "train", *a, estimates=estimates, **k))
    train_ds, train_loader = loader_of(data_dir, cfg, train=True, seed=t.seed, part="fit", pin_memory=cuda)
    eval_loader = None
    if cfg.data.val_share > 0 and t.eval_interval > 0:
        try:
            _, eval_loader = loader_of(data_dir, cfg, train=False, seed=t.seed, part="val", pin_memory=cuda)
        except FileNotFoundError as exc:
            say(f"no validation share ({exc}): periodic evaluation is off")
    else:
        say("data.val_share = 0 or train.eval_interval = 0: periodic evaluation is off")
    batches = batch_stream(train_ds, train_loader, epoch, batch_index)

    # -- logging ---------------------------------------------------------------------------------
    log_file = writer = tb = None
    if master:
        log_path = run_dir / "log.csv"
        prepare_log(log_path, step)
        log_file = open(log_path, "a", newline="")
        writer = csv.DictWriter(log_file, fieldnames=LOG_FIELDS)
        try:
            from torch.utils.tensorboard import SummaryWriter
            tb = SummaryWriter(str(run_dir / "tb"))
        except ImportError:
            tb = None

    # -- the loop --------------------------------------------------------------------------------
    say(f"training {sum(p.numel() for p in model.parameters()):,} parameters on {device} x{world}, "
        f"steps {step} -> {end} of {t.max_steps}")
    model.train()
    t0 = time.perf_counter()
    samples, loss_value, row, eval_s = 0, None, {}, 0.0

    def validate(step: int, epoch: int) -> dict:
        """The validation row of `step`; the scored weights go to best.pt when they are the best."""
        nonlocal best, eval_s
        t_eval = time.perf_counter()
        scored = checkpoint.unwrap(model) if ema is None else ema.module  # the average, when there is one
        val = evaluate(scored, eval_loader, cfg, device, autocast)
        eval_s += time.perf_counter() - t_eval
        improved, best = checkpoint.better(val, best)
        if improved and master:  # the weights validation chose (what `render --model RUN` uses)
            checkpoint.save_best(run_dir / checkpoint.BEST, scored, step, cfg, val)
        return {"step": step, "epoch": epoch, **{k: f"{v:.6g}" for k, v in val.items()}}

    def log(row: dict) -> None:
        writer.writerow(row)
        log_file.flush()
        if tb is not None:
            for k in LOG_FIELDS[2:-2]:
                if k in row:
                    tb.add_scalar(k, float(row[k]), row["step"])
        if "loss" in row:
            bar.set_postfix_str(f"step {row['step']}, loss {row['loss']}")
        if "val_loss" in row or progress.verbose():  # validation rows always, the rest with -v
            say(" ".join(f"{k} {v}" for k, v in row.items()))

    bar = progress.bar(end - step, "train", unit="step", enabled=master)  # steps: an epoch's short last batch
    #                                                                     # must not leave the bar short of 100 %
    if eval_loader is not None and step == 0:  # the start competes too (the hybrid's is the classical render)
        row = validate(0, epoch)
        if master:
            log(row)
    while step < end:
        lr = learning_rate(step, cfg)
        for group in optimizer.param_groups:
            group["lr"] = lr
        epoch, batch_index, batch = next(batches)
        b = to_device(batch, device)
        with autocast:
            loss, terms, _ = forward_loss(model, b, cfg)
        check_finite(loss, b, step, last_saved)
        scaler.scale(loss).backward()
        if t.grad_clip > 0:
            scaler.unscale_(optimizer)
            torch.nn.utils.clip_grad_norm_(model.parameters(), t.grad_clip)
        scaler.step(optimizer)
        scaler.update()
        optimizer.zero_grad(set_to_none=True)
        if ema is not None:
            ema.update(checkpoint.unwrap(model), step)
        step += 1
        samples += b["image"].shape[0] * world
        bar.update(1)
        last = step == end

        row = {}
        if step % t.log_interval == 0 or last:
            loss_value = loss.item()
            elapsed = time.perf_counter() - t0 - eval_s  # training time only
            row = {"step": step, "epoch": epoch, "lr": f"{lr:.3g}", "loss": f"{loss_value:.6g}",
                   **{k: f"{v.item():.6g}" for k, v in terms.items()},
                   "samples_per_s": f"{samples / elapsed:.3g}", "elapsed_s": f"{elapsed:.1f}"}
        if eval_loader is not None and t.eval_interval > 0 and (step % t.eval_interval == 0 or last):
            row.update(validate(step, epoch))
        if row and master:
            log(row)
        if master and (step % t.checkpoint_interval == 0 or last):
            checkpoint.save(ckpt_path, model, optimizer, step, epoch, batch_index, cfg, best, ema)
            last_saved = step

    # -- done ------------------------------------------------------------------------------------
    bar.close()
    if master:
        log_file.close()
        if tb is not None:
            tb.close()
    if ddp:  # leave the group while the interpreter is whole: first the DDP wrapper, whose reducer
        #      holds the group and its last gloo work (freed during interpreter shutdown, that work
        #      would take the GIL from a gloo thread and abort the process), then all ranks at once
        model = batches = None
        gc.collect()
        dist.barrier()
        dist.destroy_process_group()
    return {"step": step, "loss": loss_value, "val_loss": row.get("val_loss"), "best_score": best}
