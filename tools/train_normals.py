"""Trains the shipped surface-normal network (paper §3.2's "deep network") on synthetic rooms and exports it to ONNX.

    /tmp/venv-train/bin/python tools/train_normals.py \
        --cache /tmp/normals_cache.npz --n-frames 1440 --minutes 16 \
        --out panosfm_graph/models/normals.onnx

Needs the ``train`` extra (torch, onnx); the package itself only runs the
exported ONNX file with onnxruntime (:mod:`panosfm_graph.normals.onnx`).

Data (rendered once, cached as one ``.npz`` in /tmp): views of seeded
furnished box rooms (``panosfm_graph.synth.scenes.random_box_room``) only -- the named presets
``living``, ``bedroom`` and ``office`` are held out for evaluation. Each view
is rendered at twice the training size and area-downsampled (as the runner
resizes a frame), with a random camera (within 0.45 m of the room's stand
point, 1.2-1.75 m high, any yaw, pitch -25..+10 deg, roll ~3 deg, focal
0.65-0.95 x width), a random light direction for most views, random texture
strength, motion blur and noise. Targets are the renderer's camera-frame
normals (towards the camera), area-averaged and renormalised exactly as
:func:`panosfm_graph.normals.resize_normals` does for evaluation.

Training adds photometric jitter (brightness, contrast, gamma, colour gains,
an illumination ramp, noise) and horizontal flips (x of the normal negated);
3 of 4 steps use a 128x80 crop at the same scale (the coordinate channels
offset to the crop's place). Loss: mean angle between prediction and target
over valid pixels; AdamW, batch 8, cosine decay over the wall-time budget.

The network: a small U-Net (stride-2 stem, three more levels to 1/16 with a
global-context branch, normalised-coordinate input channels, output
upsampled to the input size), ~0.11 M parameters, fully convolutional with
dynamic H x W (multiples of 16 are exact; others are resized internally).
Exported with the contract of :mod:`panosfm_graph.normals.onnx`: input
``image`` float32 1x3xHxW RGB in [0, 1], output ``normals`` float32 1x3xHxW
unit camera-frame normals (OpenCV axes), checked against torch with
onnxruntime when it is importable.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import multiprocessing as mp
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

log = logging.getLogger("train_normals")

HELD_OUT = ("living", "bedroom", "office")
TRAIN_SIZE = (256, 144)  # (width, height): what the runner feeds a dynamic model at NormalsConfig.width = 256
RENDER_SCALE = 2  # render this much larger, then area-downsample


# ----------------------------------------------------------------------------------------------- data

def random_view(scene, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Returns (R_wc (3, 3), centre (3,)) of a random hand-held view near the scene's stand point."""
    stand = scene.stand_point_world
    r, a = rng.uniform(0.0, 0.45), rng.uniform(0.0, 2 * np.pi)
    center = stand + np.array([r * np.cos(a), r * np.sin(a), 0.0])
    center[2] = rng.uniform(1.2, 1.75)
    yaw = rng.uniform(-np.pi, np.pi)
    f = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    R_level = np.stack([np.cross(down, f), down, f], axis=1)  # columns: camera x, y, z in the world
    pitch = np.radians(rng.uniform(-25.0, 10.0))  # about camera x, as in synth.spin_pose
    roll = np.radians(np.clip(rng.normal(0.0, 3.0), -8.0, 8.0))
    return R_level @ Rotation.from_euler("XZ", [pitch, roll]).as_matrix(), center


def render_sample(index: int, seed: int, views_per_room: int = 6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns one training sample: (RGB uint8 (h, w, 3), normals float16 (h, w, 3), valid bool (h, w))."""
    from panosfm_graph.normals import resize_normals
    from panosfm_graph.synth import intrinsics, render_frame
    from panosfm_graph.synth.scenes import random_box_room

    cv2.setNumThreads(1)
    rng = np.random.default_rng([seed, index, 271828])
    room_seed = 10_000 + seed * 100_000 + index // views_per_room  # random rooms only; presets held out
    scene = random_box_room(room_seed)
    if rng.random() < 0.7:  # a random light from above (the renderer's default otherwise)
        light = np.array([*rng.normal(0.0, 0.6, 2), rng.uniform(0.3, 1.0)])
        scene = dataclasses.replace(scene, light_dir=light / np.linalg.norm(light))
    w, h = TRAIN_SIZE
    size = (w * RENDER_SCALE, h * RENDER_SCALE)
    K = intrinsics(size, focal_frac=0.8 if rng.random() < 0.5 else rng.uniform(0.65, 0.95))
    R_wc, c = random_view(scene, rng)
    img, _, n = render_frame(scene, K, R_wc, c, size, texture=rng.uniform(0.0, 2.0),
                             blur=rng.uniform(0.0, 6.0) if rng.random() < 0.4 else 0.0,
                             noise=rng.uniform(0.0, 6.0), seed=index)
    img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
    n, ok = resize_normals(n, h, w)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB), n.astype(np.float16), ok


def _render_chunk(indices: list[int], seed: int):
    out = [render_sample(i, seed) for i in indices]
    return indices, out


def render_dataset(n: int, seed: int = 0, workers: int = 2) -> dict[str, np.ndarray]:
    """Returns {"images" (N, h, w, 3) uint8 RGB, "normals" (N, h, w, 3) float16, "valid" (N, h, w) bool} of random rooms."""
    w, h = TRAIN_SIZE
    images = np.zeros((n, h, w, 3), np.uint8)
    normals = np.zeros((n, h, w, 3), np.float16)
    valid = np.zeros((n, h, w), bool)
    chunks = [list(range(i, min(i + 24, n))) for i in range(0, n, 24)]
    ctx = mp.get_context("fork")
    t0 = time.time()
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as ex:
        for k, (idx, out) in enumerate(ex.map(_render_chunk, chunks, [seed] * len(chunks))):
            for i, (a, b, c) in zip(idx, out):
                images[i], normals[i], valid[i] = a, b, c
            if k % 10 == 0:
                log.info("rendered %d / %d (%.0f s)", idx[-1] + 1, n, time.time() - t0)
    return {"images": images, "normals": normals, "valid": valid}


def held_out_frames(scenes=HELD_OUT, per_scene: int = 8, seed: int = 0) -> dict[str, np.ndarray]:
    """Returns held-out validation samples: spin views of the named preset rooms (same layout as render_dataset)."""
    from panosfm_graph.normals import resize_normals
    from panosfm_graph.synth import intrinsics, render_frame
    from panosfm_graph.synth.scenes import random_box_room, spin_trajectory

    w, h = TRAIN_SIZE
    size = (w * RENDER_SCALE, h * RENDER_SCALE)
    K = intrinsics(size)
    imgs, ns, oks = [], [], []
    for name in scenes:
        sc = make_scene(name, seed)
        R, c, _ = spin_trajectory(sc, 300, seed=seed)
        for f in np.linspace(0, 299, per_scene).astype(int):
            img, _, n = render_frame(sc, K, R[f], c[f], size, seed=int(f))
            img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
            n, ok = resize_normals(n, h, w)
            imgs.append(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
            ns.append(n.astype(np.float16))
            oks.append(ok)
    return {"images": np.stack(imgs), "normals": np.stack(ns), "valid": np.stack(oks)}


# ----------------------------------------------------------------------------------------------- model

def build_model():
    """Returns the torch normal network (a small U-Net; output unit camera-frame normals at the input size)."""
    import torch
    from torch import nn
    import torch.nn.functional as F

    def block(cin, cout, stride=1, dil=1):
        return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, padding=dil, dilation=dil, bias=False),
                             nn.BatchNorm2d(cout), nn.ReLU(inplace=True))

    class NormalNet(nn.Module):
        def __init__(self, c=(12, 16, 32, 48)):
            super().__init__()
            self.stem = nn.Sequential(block(3, c[0], 2), block(c[0], c[1], 2))  # 1/4
            self.e1 = block(c[1] + 2, c[1])
            self.e2 = nn.Sequential(block(c[1], c[2], 2), block(c[2], c[2]))  # 1/8
            self.e3 = nn.Sequential(block(c[2], c[3], 2), block(c[3], c[3]), block(c[3], c[3], dil=2))  # 1/16
            self.ctx = nn.Sequential(nn.Conv2d(c[3], c[3], 1), nn.ReLU(inplace=True))  # global context
            self.d2 = block(c[3] + c[2], c[2])
            self.d1 = block(c[2] + c[1], c[1])
            self.head = nn.Conv2d(c[1], 3, 3, padding=1)

        def forward(self, x, crop: tuple[int, int, int, int] | None = None):
            """``crop`` (training only) = (y0, x0, full H, full W) when ``x`` is a crop (offsets multiples of 16)."""
            H, W = x.shape[2], x.shape[3]
            s = self.stem(x)
            h4, w4 = s.shape[2], s.shape[3]
            oy, ox, fh, fw = (0, 0, h4, w4) if crop is None else (crop[0] // 4, crop[1] // 4, crop[2] // 4, crop[3] // 4)
            # normalised image coordinates (x / (W/2), y / (W/2)) of the full frame: where in the image a pixel lies
            xs = (torch.arange(w4, dtype=x.dtype) + (ox - (fw - 1) * 0.5)) / (fw * 0.5)
            ys = (torch.arange(h4, dtype=x.dtype) + (oy - (fh - 1) * 0.5)) / (fw * 0.5)
            gx = xs.view(1, 1, 1, -1).expand(1, 1, h4, w4)
            gy = ys.view(1, 1, -1, 1).expand(1, 1, h4, w4)
            coords = torch.cat([gx, gy], 1).expand(s.shape[0], 2, h4, w4)
            f1 = self.e1(torch.cat([s, coords], 1))
            f2 = self.e2(f1)
            f3 = self.e3(f2)
            f3 = f3 + self.ctx(f3.mean(dim=(2, 3), keepdim=True))

            def up(a, like):
                return F.interpolate(a, size=(like.shape[2], like.shape[3]), mode="bilinear", align_corners=False)

            y = self.d2(torch.cat([up(f3, f2), f2], 1))
            y = self.d1(torch.cat([up(y, f1), f1], 1))
            y = F.interpolate(self.head(y), size=(H, W), mode="bilinear", align_corners=False)
            return y / torch.sqrt((y * y).sum(1, keepdim=True) + 1e-8)

    return NormalNet()


# ----------------------------------------------------------------------------------------------- training

def augment(x, n, rng: np.random.Generator):
    """Returns photometrically jittered images (B, 3, h, w) in [0, 1] and the normals, randomly h-flipped."""
    import torch

    B, _, h, w = x.shape
    g = lambda lo, hi, *s: torch.from_numpy(rng.uniform(lo, hi, (B, *s)).astype(np.float32))  # noqa: E731
    x = x.clamp(1e-4, 1) ** g(0.7, 1.4, 1, 1, 1)
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    x = (x - mean) * g(0.7, 1.3, 1, 1, 1) + mean
    x = x * g(0.6, 1.4, 1, 1, 1) * g(0.85, 1.15, 3, 1, 1)
    ramp_x = torch.linspace(-1, 1, w).view(1, 1, 1, w) * g(-0.15, 0.15, 1, 1, 1)
    ramp_y = torch.linspace(-1, 1, h).view(1, 1, h, 1) * g(-0.15, 0.15, 1, 1, 1)
    x = x * (1 + ramp_x + ramp_y)
    x = x + torch.randn_like(x) * g(0.0, 0.02, 1, 1, 1)
    flip = torch.from_numpy(rng.random(B) < 0.5)
    if flip.any():
        x[flip] = x[flip].flip(3)
        nf = n[flip].flip(3)
        nf[:, 0] = -nf[:, 0]
        n[flip] = nf
    return x.clamp(0, 1), n


def angular_error_deg(pred, target, valid):
    """Returns the (M,) angles in degrees between predicted and target normals over valid pixels."""
    import torch

    cos = (pred * target).sum(1)[valid].clamp(-1, 1)
    return torch.rad2deg(torch.acos(cos))


def evaluate(model, data: dict[str, np.ndarray], batch: int = 8) -> dict[str, float]:
    """Returns median angular error (deg) and share within 20 deg of ``model`` on ``data``."""
    import torch

    model.eval()
    errs = []
    with torch.no_grad():
        for i in range(0, len(data["images"]), batch):
            x = torch.from_numpy(data["images"][i:i + batch]).permute(0, 3, 1, 2).float() / 255.0
            n = torch.from_numpy(data["normals"][i:i + batch].astype(np.float32)).permute(0, 3, 1, 2)
            ok = torch.from_numpy(data["valid"][i:i + batch])
            errs.append(angular_error_deg(model(x), n, ok))
    e = torch.cat(errs).numpy()
    model.train()
    return {"median_deg": float(np.median(e)), "within_20deg": float(np.mean(e < 20.0))}


def train(model, data: dict[str, np.ndarray], val: dict[str, np.ndarray], minutes: float, batch: int = 8,
          lr: float = 1e-3, seed: int = 0, crop_share: float = 0.75, crop_hw: tuple[int, int] = (80, 128)
          ) -> list[dict]:
    """Returns the training log; trains ``model`` in place for ``minutes`` of wall time (AdamW, cosine schedule).

    A share ``crop_share`` of the steps trains on a ``crop_hw`` crop of the batch (same scale, the
    coordinate channels offset to the crop's place in the frame): more steps for the same compute.
    """
    import torch

    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    N = len(data["images"])
    budget = minutes * 60.0
    t0 = time.time()
    history, step, perm, pos = [], 0, rng.permutation(N), 0
    next_eval = 0.0
    while True:
        frac = (time.time() - t0) / budget
        if frac >= 1.0:
            break
        for gparam in opt.param_groups:  # cosine decay with a short warm-up, by elapsed time
            gparam["lr"] = lr * min(1.0, 20 * frac + 0.05) * 0.5 * (1 + np.cos(np.pi * frac))
        if pos + batch > N:
            perm, pos = rng.permutation(N), 0
        idx = np.sort(perm[pos:pos + batch])
        pos += batch
        x = torch.from_numpy(data["images"][idx]).permute(0, 3, 1, 2).float() / 255.0
        n = torch.from_numpy(data["normals"][idx].astype(np.float32)).permute(0, 3, 1, 2)
        ok = torch.from_numpy(data["valid"][idx])
        x, n = augment(x, n, rng)
        crop = None
        if rng.random() < crop_share:  # a same-scale crop: ~3.5x cheaper steps, coordinates kept
            H, W = x.shape[2], x.shape[3]
            ch, cw = crop_hw
            y0, x0 = 16 * int(rng.integers(0, (H - ch) // 16 + 1)), 16 * int(rng.integers(0, (W - cw) // 16 + 1))
            x, n, ok = x[:, :, y0:y0 + ch, x0:x0 + cw], n[:, :, y0:y0 + ch, x0:x0 + cw], ok[:, y0:y0 + ch, x0:x0 + cw]
            crop = (y0, x0, H, W)
        pred = model(x, crop)
        cos = (pred * n).sum(1)[ok].clamp(-0.9999, 0.9999)
        loss = torch.acos(cos).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        step += 1
        if time.time() - t0 >= next_eval or step == 1:
            m = evaluate(model, val)
            rec = {"step": step, "epoch": step * batch / N, "s": round(time.time() - t0, 1),
                   "loss_deg": float(np.degrees(loss.item())), **{f"val_{k}": v for k, v in m.items()}}
            history.append(rec)
            log.info("%s", json.dumps(rec))
            next_eval += 60.0
    m = evaluate(model, val)
    history.append({"step": step, "epoch": step * batch / N, "s": round(time.time() - t0, 1),
                    **{f"val_{k}": v for k, v in m.items()}})
    log.info("final %s", json.dumps(history[-1]))
    return history


# ----------------------------------------------------------------------------------------------- export

def export_onnx(model, path: Path, opset: int = 17) -> Path:
    """Returns ``path`` after writing ``model`` as ONNX (input ``image`` 1x3xHxW RGB [0, 1], output ``normals``)."""
    import torch

    model.eval()
    path.parent.mkdir(parents=True, exist_ok=True)
    x = torch.rand(1, 3, TRAIN_SIZE[1], TRAIN_SIZE[0])
    torch.onnx.export(model, (x,), str(path), opset_version=opset, input_names=["image"], output_names=["normals"],
                      dynamic_axes={"image": {2: "H", 3: "W"}, "normals": {2: "H", 3: "W"}}, dynamo=False,
                      do_constant_folding=True)
    import onnx

    onnx.checker.check_model(onnx.load(str(path)))
    return path


def check_onnx(model, path: Path, sizes=((144, 256), (96, 160), (192, 256))) -> float:
    """Returns the largest |onnxruntime - torch| over test inputs of several sizes (inf if onnxruntime is missing)."""
    import torch

    try:
        import onnxruntime as ort
    except ImportError:
        log.warning("onnxruntime not importable here: ONNX output not checked against torch")
        return float("inf")
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    worst = 0.0
    model.eval()
    for h, w in sizes:
        x = torch.rand(1, 3, h, w)
        with torch.no_grad():
            ref = model(x).numpy()
        out = sess.run(None, {"image": x.numpy()})[0]
        assert out.shape == ref.shape, (out.shape, ref.shape)
        worst = max(worst, float(np.abs(out - ref).max()))
    return worst


def main(argv=None) -> int:
    import torch

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default="/tmp/normals_cache.npz", help="rendered training data (made if missing)")
    ap.add_argument("--n-frames", type=int, default=1440, help="training views to render")
    ap.add_argument("--minutes", type=float, default=16.0, help="training wall time")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--checkpoint", default="/tmp/normals_model.pt", help="torch state_dict written after training")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--crop-share", type=float, default=0.75, help="share of steps on 128x80 crops")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="panosfm_graph/models/normals.onnx")
    ap.add_argument("--log", default="/tmp/normals_train.json", help="training log JSON")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(1)

    cache = Path(args.cache)
    if cache.is_file():
        data = dict(np.load(cache))
        log.info("loaded %d cached views from %s", len(data["images"]), cache)
    else:
        t = time.time()
        data = render_dataset(args.n_frames, args.seed, workers=args.threads)
        np.savez(cache, **data)
        log.info("rendered %d views in %.0f s -> %s", args.n_frames, time.time() - t, cache)
    val = held_out_frames()
    model = build_model()
    log.info("model: %d parameters", sum(p.numel() for p in model.parameters()))
    history = train(model, data, val, args.minutes, args.batch, args.lr, args.seed, args.crop_share)
    torch.save(model.state_dict(), args.checkpoint)
    out = export_onnx(model, Path(args.out))
    diff = check_onnx(model, out)
    log.info("exported %s (%.2f MB); max |onnx - torch| = %.2e", out, out.stat().st_size / 1e6, diff)
    log_path = Path(args.log)
    log_path.write_text(json.dumps({"args": vars(args), "max_abs_onnx_torch": diff, "history": history}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
