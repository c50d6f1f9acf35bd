"""The spatiotemporal force regressor: marker-image sequence -> (Fx, Fy, Fz) per frame.

The paper's architecture (RAFT feature encoder -> ConvGRU -> residual blocks -> average pool
-> linear -> sigmoid over min-max normalised forces) at CPU size:

  input   (T, C, S, S) per contact sequence, S = ``input_size`` (the uint8 0/255 marker images
          are area-resized to S x S inside :func:`prepare`)
  encoder conv7x7 stride 2 -> one stride-2 residual block per ``encoder_channels`` entry ->
          1x1 conv: (hidden, G, G), G = S / 2^(1 + len(encoder_channels)) (4 at the defaults)
  ConvGRU 3x3 on that grid, state carried from frame to frame (from zeros at contact start)
  head    one stride-2 residual block per ``head_channels`` entry -> average pool -> linear
          -> 3 -> sigmoid

RAFT keeps its GRU at 1/8 resolution with 128 channels; on a 2-core CPU the GRU then costs
more than everything else, so the CPU profile downsamples once more (1/16) and narrows the
channels (benchmarks/force.py measures its speed).

Input representation (``input_mode``): "difference" feeds one channel, (image - reference)/255,
so the static marker layout cancels and only marker motion remains; "stack" feeds the image and
the reference as two channels, which keys the model on one sensor's marker layout.

Mirror read (``mirror_read``, "none" by default; genforce_plus's `mirror_shear`): shear is odd
under a mirror image of the contact (the columns reversed negate Fx, the rows reversed Fy) and
the normal force even.  With "auto" a model reads each frame also as the mirror images under
which its sensor's reference looks the same (:func:`mirror_group`: correlation >= MIRROR_MATCH
at the input size), in one batch, and its shear is the mean of the readings with the mirrored
axes' signs undone: the odd part, which cancels an even error.  Fz stays the frame's own
reading.  A reference that no mirror leaves alike reads as with "none": its mirror images would
be contacts on markers the sensor lacks.

Outputs are min-max normalised per axis over [force_min, force_max] (labels outside are
clipped), so the sigmoid's range is the force range.  force_min = force_max = "auto" (the
paper's min-max normalisation of the training labels) has train.fit set the range from the
labels it trains on, widened by ``range_margin`` of the span on each side (so that a model
can read a contact somewhat harder than any it trained on); the fitted range is
part of the stored config.  Sensors differ a lot in range (TacTip shear within +-1 N, uSkin
normal force to -56 N), so a fixed range either clips one or leaves another a sliver of the
sigmoid.  The model carries a ``reference`` buffer:
the no-contact image of the sensor it was trained for, used when no reference is passed at
prediction time.  Weights serialise to plain arrays (:func:`to_arrays` / :func:`from_arrays`).
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from stages.common import attrs_of, check_option, marker_images

DEFAULT_CONFIG = {
    "input_size": 64,                     # side S of the area-resized input images
    "input_mode": "difference",           # "difference" (1 channel) or "stack" (image, reference)
    "stem_channels": 8,                   # conv7x7 stride 2 -> S/2
    "encoder_channels": [16, 24, 32],     # stride-2 residual blocks -> S/4, S/8, S/16
    "hidden": 32,                         # ConvGRU state channels (also the encoder's output)
    "head_channels": [48, 64],            # stride-2 residual blocks after the GRU
    "force_min": [-5.0, -5.0, -20.0],     # N, min-max normalisation (paper's ranges)
    "force_max": [5.0, 5.0, 5.0],
    "mirror_read": "none",                # "auto": shear read over the reference's mirror group
    "range_margin": 0.05,                 # "auto" range: label min/max widened by this share of the span
}
INPUT_MODES = ("difference", "stack")
MIRROR_READS = ("auto", "none")
# mirror image -> (image dims reversed, force axes negated): columns are x, rows y
MIRRORS = {"x": ((-1,), (0,)), "y": ((-2,), (1,)), "xy": ((-1, -2), (0, 1))}
MIRROR_MATCH = 0.9          # a mirror is a symmetry of the reference at this correlation or above
AUTO = "auto"


def model_config(config: Mapping | None = None) -> dict:
    """DEFAULT_CONFIG with the given keys replaced; unknown keys or bad values raise."""
    config = dict(config or {})
    unknown = sorted(set(config) - set(DEFAULT_CONFIG))
    if unknown:
        raise KeyError(f"unknown force-model config key(s) {unknown} (known: {sorted(DEFAULT_CONFIG)})")
    out = {**DEFAULT_CONFIG, **config}
    out = {k: (list(v) if isinstance(v, (list, tuple, np.ndarray)) else v) for k, v in out.items()}
    check_option("force.config.input_mode", out["input_mode"], INPUT_MODES)
    check_option("force model mirror_read", out["mirror_read"], MIRROR_READS)
    down = 2 ** (1 + len(out["encoder_channels"]))
    if int(out["input_size"]) % down:
        raise ValueError(f"input_size {out['input_size']} must be a multiple of {down} "
                         f"(the encoder's {len(out['encoder_channels'])} stride-2 stages after the stem)")
    out["input_size"], out["hidden"] = int(out["input_size"]), int(out["hidden"])
    margin = out["range_margin"]
    if isinstance(margin, bool) or not isinstance(margin, (int, float)) or not 0.0 <= float(margin) <= 10.0:
        raise ValueError(f"force model range_margin {margin!r} must be a number in [0, 10]")
    out["range_margin"] = float(margin)
    auto = [isinstance(out[k], str) and out[k] == AUTO for k in ("force_min", "force_max")]
    if all(auto):
        return out
    if any(isinstance(out[k], str) for k in ("force_min", "force_max")):
        raise ValueError(f"force_min {out['force_min']!r} / force_max {out['force_max']!r}: "
                         f"3 numbers each, or both {AUTO!r}")
    lo, hi = np.asarray(out["force_min"], float), np.asarray(out["force_max"], float)
    if lo.shape != (3,) or hi.shape != (3,) or np.any(hi <= lo):
        raise ValueError(f"force_min {out['force_min']} / force_max {out['force_max']}: "
                         "need 3 values each, max > min")
    out["force_min"], out["force_max"] = lo.tolist(), hi.tolist()
    return out


def resolve_range(config: Mapping, force) -> dict:
    """The config with an "auto" force range set from labels `force` (N,3): per axis
    min - range_margin * span .. max + range_margin * span (an axis spanning under 1 mN gets
    +-0.5 N around its value).  A numeric range is returned unchanged."""
    config = model_config(config)
    if config["force_min"] != AUTO:
        return config
    f = np.asarray(force, float).reshape(-1, 3)
    if not f.size or not np.all(np.isfinite(f)):
        raise ValueError("force range 'auto': the training labels are empty or not finite")
    lo, hi = f.min(0), f.max(0)
    span = hi - lo
    narrow = span < 1e-3
    pad = np.where(narrow, 0.5, float(config["range_margin"]) * span)
    return model_config({**config, "force_min": (lo - pad).round(6).tolist(),
                         "force_max": (hi + pad).round(6).tolist()})


# ---------------------------------------------------------------------------- layers

class ResidualBlock(nn.Module):
    """Two 3x3 convs with batch norm; a 1x1 projection when the shape changes."""

    def __init__(self, c_in: int, c_out: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(c_out)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(c_out)
        self.skip = (nn.Sequential(nn.Conv2d(c_in, c_out, 1, stride, bias=False), nn.BatchNorm2d(c_out))
                     if stride != 1 or c_in != c_out else nn.Identity())

    def forward(self, x):
        y = F.relu(self.bn1(self.conv1(x)))
        return F.relu(self.bn2(self.conv2(y)) + self.skip(x))


class Encoder(nn.Module):
    """RAFT-style feature encoder: conv7x7/2 -> stride-2 residual stages -> 1x1."""

    def __init__(self, c_in: int, stem: int, channels, out: int):
        super().__init__()
        self.stem = nn.Sequential(nn.Conv2d(c_in, stem, 7, 2, 3, bias=False), nn.BatchNorm2d(stem), nn.ReLU())
        blocks, prev = [], stem
        for ch in channels:
            blocks.append(ResidualBlock(prev, int(ch), 2))
            prev = int(ch)
        self.stages = nn.Sequential(*blocks)
        self.out = nn.Conv2d(prev, out, 1)

    def forward(self, x):
        return self.out(self.stages(self.stem(x)))


class ConvGRU(nn.Module):
    """Convolutional GRU cell (3x3), as in RAFT's update block."""

    def __init__(self, hidden: int, c_in: int):
        super().__init__()
        self.gates = nn.Conv2d(hidden + c_in, 2 * hidden, 3, 1, 1)
        self.cand = nn.Conv2d(hidden + c_in, hidden, 3, 1, 1)

    def forward(self, h, x):
        z, r = torch.sigmoid(self.gates(torch.cat([h, x], 1))).chunk(2, 1)
        q = torch.tanh(self.cand(torch.cat([r * h, x], 1)))
        return (1 - z) * h + z * q


class ForceRegressor(nn.Module):
    """Per-frame 3-axis force from a marker-image sequence, GRU state carried across frames."""

    def __init__(self, config: Mapping | None = None):
        super().__init__()
        self.config = model_config(config)
        c = self.config
        if c["force_min"] == AUTO:
            raise ValueError("force range 'auto' is set from the training labels "
                             "(stages.force.train.fit, or model.resolve_range) before a model is built")
        c_in = 1 if c["input_mode"] == "difference" else 2
        hidden = c["hidden"]
        self.encoder = Encoder(c_in, int(c["stem_channels"]), c["encoder_channels"], hidden)
        self.gru = ConvGRU(hidden, hidden)
        blocks, prev = [], hidden
        for ch in c["head_channels"]:
            blocks.append(ResidualBlock(prev, int(ch), 2))
            prev = int(ch)
        self.head = nn.Sequential(*blocks)
        self.linear = nn.Linear(prev, 3)
        self.register_buffer("force_min", torch.tensor(c["force_min"], dtype=torch.float32))
        self.register_buffer("force_max", torch.tensor(c["force_max"], dtype=torch.float32))
        self.register_buffer("reference", torch.zeros(0, 0, dtype=torch.uint8))

    @property
    def state_shape(self) -> tuple[int, int, int]:
        s = self.config["input_size"] // 2 ** (1 + len(self.config["encoder_channels"]))
        return (self.config["hidden"], s, s)

    def set_reference(self, reference) -> None:
        """Store the trained-for sensor's no-contact image (H,W) uint8 with the weights."""
        ref = np.asarray(reference)
        if ref.ndim != 2 or ref.dtype != np.uint8:
            raise ValueError(f"reference must be a (H,W) uint8 image, got {ref.dtype} {ref.shape}")
        self.reference = torch.from_numpy(ref.copy())

    def _head(self, h):
        y = self.head(h).mean(dim=(2, 3))
        return torch.sigmoid(self.linear(y))

    def mirrors_for(self, reference) -> tuple[str, ...]:
        """The mirror images this model reads a frame as, for a sensor whose no-contact image
        is `reference` (H,W): mirror_group at the input size, or () with mirror_read "none"."""
        if self.config["mirror_read"] == "none":
            return ()
        return mirror_group(reference, self.config["input_size"])

    def _with_mirrors(self, x, mirrors):
        """x (B,...,S,S) -> the batch followed by each mirror image of it ((1 + M) B, ...)."""
        return torch.cat([x] + [torch.flip(x, MIRRORS[m][0]) for m in mirrors]) if mirrors else x

    def _mirror_mean(self, y, mirrors, b: int):
        """Normalised outputs of a _with_mirrors batch -> (B,...,3): shear the mean of the
        readings with each mirror's axes negated back, Fz the unmirrored frame's."""
        if not mirrors:
            return y
        y = y.unflatten(0, (1 + len(mirrors), b))
        f = self.denormalise(y).clone()
        for k, m in enumerate(mirrors, 1):
            f[k, ..., list(MIRRORS[m][1])] *= -1
        return torch.cat([self.normalise(f.mean(0))[..., :2], y[0, ..., 2:]], -1)

    def forward(self, x, h=None, mirrors: Sequence[str] = ()):
        """x (B,T,C,S,S) prepared inputs -> (normalised forces (B,T,3) in [0,1], last state).
        ``mirrors`` (mirrors_for): the shear read over these mirror images of x too; the state
        then holds every image's, (1 + len(mirrors)) B of them."""
        b0 = x.shape[0]
        x = self._with_mirrors(x, mirrors)
        b, t = x.shape[:2]
        feats = self.encoder(x.flatten(0, 1)).unflatten(0, (b, t))
        if h is None:
            h = feats.new_zeros((b,) + self.state_shape)
        states = []
        for k in range(t):
            h = self.gru(h, feats[:, k])
            states.append(h)
        out = self._head(torch.stack(states, 1).flatten(0, 1)).unflatten(0, (b, t))
        return self._mirror_mean(out, mirrors, b0), h

    def step(self, x, h=None, mirrors: Sequence[str] = ()):
        """One frame: x (B,C,S,S) -> (normalised forces (B,3), new state); ``mirrors`` as forward's."""
        b0 = x.shape[0]
        x = self._with_mirrors(x, mirrors)
        feats = self.encoder(x)
        if h is None:
            h = feats.new_zeros((x.shape[0],) + self.state_shape)
        h = self.gru(h, feats)
        return self._mirror_mean(self._head(h), mirrors, b0), h

    # -- label normalisation
    def normalise(self, force):
        """Forces (..., 3) N -> [0, 1] per axis, clipped to the configured range."""
        lo, hi = self.force_min, self.force_max
        return ((torch.as_tensor(force, dtype=torch.float32) - lo) / (hi - lo)).clamp(0.0, 1.0)

    def denormalise(self, y):
        return self.force_min + y * (self.force_max - self.force_min)


def mirror_group(reference, size: int) -> tuple[str, ...]:
    """The mirror images ("x": columns reversed, "y": rows reversed, "xy": both) under which a
    sensor's no-contact image (H,W), area-resized to size x size as the model sees it, looks
    the same: Pearson correlation with its mirror image >= MIRROR_MATCH (GelSight A-II 0.99,
    TacTip 0.998, uSkin 1.0, D-I 0.93/0.93/0.996; C-II only "y", 0.996 against 0.78 for "x";
    A-I and C-I none, <= 0.31).  A uniform image has no pattern to match: ()."""
    ref = _resize(np.asarray(reference, np.uint8)[None], int(size))[0, 0]
    ref = ref - ref.mean()
    norm = float((ref * ref).sum())
    if norm <= 0.0:
        return ()
    return tuple(m for m, (dims, _) in MIRRORS.items()
                 if float((ref * torch.flip(ref, dims)).sum()) / norm >= MIRROR_MATCH)


# ---------------------------------------------------------------------------- inputs

def _resize(images: np.ndarray, size: int) -> torch.Tensor:
    """uint8 (T,H,W) -> float (T,1,size,size) in [0,1], area-averaged (adaptive average pool)."""
    x = torch.from_numpy(np.ascontiguousarray(images, dtype=np.uint8)).float().div_(255.0)[:, None]
    if x.shape[-2:] != (size, size):
        x = F.adaptive_avg_pool2d(x, size)
    return x


def prepare(images, reference, config: Mapping) -> torch.Tensor:
    """Marker images (T,H,W) uint8 0/255 + the sensor's reference (H,W) -> model input (T,C,S,S)."""
    images = marker_images(images, "force model images")
    if images.ndim == 2:
        images = images[None]
    reference = marker_images(reference, "force model reference", (2,))
    if reference.shape != images.shape[1:]:
        raise ValueError(f"images {images.shape} and reference {reference.shape} must be (T,H,W) and (H,W)")
    size = int(config["input_size"])
    x, ref = _resize(images, size), _resize(reference[None], size)
    if config["input_mode"] == "difference":
        return x - ref
    return torch.cat([x, ref.expand_as(x)], 1)


def _reference_for(model: ForceRegressor, reference):
    if reference is not None:
        return np.asarray(reference)
    if model.reference.numel() == 0:
        raise ValueError("no reference image: pass one, or set it with model.set_reference()")
    return model.reference.cpu().numpy()


# ---------------------------------------------------------------------------- prediction

@torch.no_grad()
def predict_sequence(model: ForceRegressor, images, reference=None, *, chunk: int = 256) -> np.ndarray:
    """Forces (T,3) N for one contact sequence (T,H,W), GRU state from zeros at frame 0, on the
    model's device; shear read over the reference's mirror images (ForceRegressor.mirrors_for)."""
    model.eval()
    ref = _reference_for(model, reference)
    mirrors = model.mirrors_for(ref)
    dev = model.force_min.device
    images = np.asarray(images)
    out, h = [], None
    for a in range(0, len(images), chunk):
        y, h = model(prepare(images[a:a + chunk], ref, model.config)[None].to(dev), h, mirrors)
        out.append(model.denormalise(y[0]).cpu())
    if not out:
        return np.zeros((0, 3), np.float32)
    return torch.cat(out).numpy().astype(np.float32)


@torch.no_grad()
def predict_contacts(model: ForceRegressor, images, contact_id, reference=None, *,
                     batch: int = 16) -> np.ndarray:
    """Forces (N,3) N for frames of many contacts, the state reset at every contact, computed
    on the model's device (load_model(..., device=)).

    Frames of one contact must be contiguous and in time order (as in a contact-sequence
    artifact).  Contacts are run side by side in batches, padded with their last frame;
    the GRU is causal, so padding never changes a real frame's output.  Shear is read over the
    reference's mirror images (ForceRegressor.mirrors_for).
    """
    model.eval()
    ref = _reference_for(model, reference)
    mirrors = model.mirrors_for(ref)
    dev = model.force_min.device
    contact_id = np.asarray(contact_id)
    if contact_id.ndim != 1 or contact_id.size != len(images):
        raise ValueError(f"contact_id {contact_id.shape} must give one contact per frame of images "
                         f"{np.shape(images)}")
    starts = np.flatnonzero(np.r_[True, contact_id[1:] != contact_id[:-1]])
    ends = np.r_[starts[1:], contact_id.size]
    out = np.zeros((contact_id.size, 3), np.float32)
    for i in range(0, starts.size, batch):
        runs = list(zip(starts[i:i + batch], ends[i:i + batch]))
        length = max(e - s for s, e in runs)
        x = torch.stack([_pad(prepare(np.asarray(images[s:e]), ref, model.config), length)
                         for s, e in runs]).to(dev)
        y = model.denormalise(model(x, None, mirrors)[0]).cpu().numpy()
        for k, (s, e) in enumerate(runs):
            out[s:e] = y[k, :e - s]
    return out


def _pad(x: torch.Tensor, length: int) -> torch.Tensor:
    """Pad a (T,...) tensor to `length` frames by repeating its last frame."""
    if len(x) >= length:
        return x[:length]
    return torch.cat([x, x[-1:].expand((length - len(x),) + tuple(x.shape[1:]))])


class StreamingPredictor:
    """Frame-by-frame force for a control loop: the GRU state is carried between calls.

    ``reference`` is the sensor's no-contact image; by default the one stored with the model.
    Call :meth:`reset` when a new contact (or session) starts.  Shear is read over the
    reference's mirror images (ForceRegressor.mirrors_for), in the same batch as the frame.
    """

    def __init__(self, model: ForceRegressor, reference=None):
        self.model = model.eval()
        self._dev = model.force_min.device          # the model's device (a control loop's: the CPU)
        self._ref = marker_images(_reference_for(model, reference), "StreamingPredictor reference", (2,))
        self._ref_input = _resize(self._ref[None], model.config["input_size"]).to(self._dev)
        self.mirrors = model.mirrors_for(self._ref)
        self.h = None

    def reset(self, reference=None) -> None:
        """Forget the contact history (and optionally take a new reference image)."""
        self.h = None
        if reference is not None:
            self._ref = marker_images(reference, "StreamingPredictor reference", (2,))
            self._ref_input = _resize(self._ref[None], self.model.config["input_size"]).to(self._dev)
            self.mirrors = self.model.mirrors_for(self._ref)

    @torch.no_grad()
    def step(self, image) -> np.ndarray:
        """One (H,W) uint8 marker image -> (Fx, Fy, Fz) N as a (3,) float32 array."""
        image = marker_images(image, "StreamingPredictor.step image", (2,))
        if image.shape != self._ref.shape:
            raise ValueError(f"image {image.shape} does not match the reference {self._ref.shape}")
        x = _resize(image[None], self.model.config["input_size"]).to(self._dev)
        if self.model.config["input_mode"] == "difference":
            x = x - self._ref_input
        else:
            x = torch.cat([x, self._ref_input], 1)
        y, self.h = self.model.step(x, self.h, self.mirrors)
        return self.model.denormalise(y[0]).cpu().numpy().astype(np.float32)


# ---------------------------------------------------------------------------- serialisation

def to_arrays(model: ForceRegressor) -> dict[str, np.ndarray]:
    """Every parameter and buffer as a numpy array, keyed by its state-dict name (scalars,
    e.g. batch-norm step counters, as shape (1,): stores read 0-d datasets back as scalars)."""
    return {k: v.detach().cpu().numpy().reshape(v.shape or (1,)).copy()
            for k, v in model.state_dict().items()}


def from_arrays(arrays: Mapping, config: Mapping) -> ForceRegressor:
    """Rebuild a model (in eval mode) from :func:`to_arrays` output and its config."""
    model = ForceRegressor(config)
    missing = sorted(set(model.state_dict()) - set(arrays))
    extra = sorted(set(arrays) - set(model.state_dict()))
    if missing or extra:
        raise KeyError(f"force-model arrays do not match the config: missing {missing[:5]}, "
                       f"unexpected {extra[:5]}")
    model.reference = torch.from_numpy(np.array(arrays["reference"], np.uint8))
    state = model.state_dict()
    model.load_state_dict({k: torch.from_numpy(np.array(arrays[k]).reshape(v.shape)) for k, v in state.items()})
    return model.eval()


def _stored_arrays(art, prefix: str) -> dict:
    """The arrays of a model group: a nested dict (node output) or 'prefix/name' datasets."""
    try:
        sub = art[prefix]
    except KeyError:          # a store artifact lists datasets by full name: 'prefix/...'
        sub = None
    if isinstance(sub, Mapping):
        return {k: np.asarray(v) for k, v in sub.items()}
    head = prefix + "/"
    out = {k[len(head):]: np.asarray(art[k][()]) for k in art if k.startswith(head)}
    if not out:
        raise KeyError(f"no force-model arrays under {prefix!r} in the artifact")
    return out


def load_model(art, prefix: str = "weights", device=None) -> ForceRegressor:
    """The regressor stored in an own ("weights") or transfer ("genforce", "genforce_comp",
    "genforce_plus") artifact, or in such a node's output dict; eval mode, on `device` (default
    the CPU).  A group's own config (attrs configs[prefix]) wins over the artifact's config."""
    attrs = attrs_of(art)
    config = (attrs.get("configs") or {}).get(prefix) or attrs.get("config")
    if config is None:
        raise KeyError("the artifact has no attrs['config'] for its force model")
    model = from_arrays(_stored_arrays(art, prefix), config)
    return model.to(device) if device is not None else model


def load_predictor(art, prefix: str = "weights", reference=None) -> StreamingPredictor:
    """A StreamingPredictor on a stored model (reference: the one stored with it by default)."""
    return StreamingPredictor(load_model(art, prefix), reference)
