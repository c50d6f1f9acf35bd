"""Node `markers[skin]`: every skin's frames as binary marker images, the common currency of
GenForce (white markers on black, (N,H,W) uint8 0/255, plus the no-contact `reference`).

The skin's `look` (params `skins.<name>.look`) says how its source becomes marker images:
  none      the render is already the marker image: images = truth, reference = truth_reference
  gelsight  camera frames, dark markers on a lit gel: images = segment(raw), reference =
  tactip    segment(raw_reference) (bright pins on a dark dome for tactip); the ground truth
            scores the segmentation: metrics segment/<skin>/iou and segment/<skin>/centroid_px,
            means over frames
  taxel     uSkin counts: images = signal_to_marker(signals, baseline), reference =
            signal_to_marker(baseline)
Per-frame label keys are copied unchanged (and `indenters`, the names `indenter_id` indexes);
frames stream in chunks, so memory does not grow with N.
"""
from __future__ import annotations

from typing import Mapping

import numpy as np

from stages.markers.uskin import LABEL_KEYS, USKIN_PAD_MM, signal_to_marker

LOOKS = ("none", "gelsight", "tactip", "taxel")
POLARITY = {"gelsight": "dark", "tactip": "bright"}
TAXEL_KEYS = ("s_xy", "s_z", "base_area", "min_area", "max_area", "max_offset")
CHUNK = 64          # frames per streamed chunk
EXAMPLES = 4        # frames shown in figures/examples


def segmentation_params(segmentation: Mapping, look: str) -> dict:
    """segment() keyword arguments for a camera look: the top-level entries of `segmentation`
    are shared defaults, `segmentation[look]` (a mapping) overrides them, other looks'
    sections are ignored, and polarity defaults to the look's (gelsight dark, tactip bright)."""
    shared = {k: v for k, v in segmentation.items() if not isinstance(v, Mapping)}
    return {"polarity": POLARITY[look], **shared, **dict(segmentation.get(look, {}))}


def _need(source: Mapping, names, skin: str, look: str) -> None:
    missing = [n for n in names if n not in source]
    if missing:
        raise KeyError(f"markers[{skin}]: look {look!r} needs {', '.join(missing)} in its source "
                       f"(has {', '.join(sorted(source))})")


def _example_frames(source: Mapping, n: int, k: int = EXAMPLES) -> list[int]:
    """k frames spread over the sequence, each moved to the deepest frame of its contact."""
    if n == 0:
        return []
    picks = ((np.arange(min(k, n)) + 0.5) * n / min(k, n)).astype(int)
    if "depth" in source and "contact_id" in source:
        depth, contact = np.asarray(source["depth"]), np.asarray(source["contact_id"])
        picks = [int(np.flatnonzero(contact == contact[i])[np.argmax(depth[contact == contact[i]])])
                 for i in picks]
    return sorted(set(int(i) for i in picks))


def _taxel_settings(source: Mapping, spec: Mapping, skin: str) -> dict:
    if "size" not in spec:
        raise KeyError(f"markers[{skin}]: the taxel look needs `size` ([H, W]) in the skin's params")
    attrs = getattr(source, "attrs", {}) or {}
    pad = spec.get("pad_mm", attrs.get("pad_mm", USKIN_PAD_MM))
    variant = spec.get("variant", attrs.get("variant", "3axis"))
    return {"size": tuple(int(v) for v in spec["size"]), "pad_mm": tuple(float(v) for v in pad),
            "z_only": variant == "z", **{k: float(spec[k]) for k in TAXEL_KEYS if k in spec}}


def marker_sequence(*, source: Mapping, skin: str, spec: Mapping, segmentation: Mapping):
    """Node `markers[skin]`: yields chunks of `images` (n,H,W) uint8 0/255 with the label keys;
    returns `reference` (H,W), `indenters` (when the source has it), figures/examples, attrs and,
    for camera looks, the segmentation metrics.

    source: a render[skin] artifact (truth, raw, truth_reference, raw_reference, labels) or a
    taxels[skin] artifact (signals, baseline, labels).  spec: the skin's params; uses `look`,
    and for the taxel look `size` [H, W] plus the optional signal_to_marker constants s_xy,
    s_z, base_area, min_area, max_area, max_offset, and `pad_mm` / `variant` (default: the source's
    attrs; variant "z" draws z-only dots).  segmentation: segment() parameters, see
    segmentation_params.
    """
    from tqdm import tqdm

    from stages.figures import contact_sheet, png
    from stages.markers.segment import centroid_error, iou, segment

    look = spec.get("look")
    if look not in LOOKS:
        raise ValueError(f"markers[{skin}]: look must be one of {LOOKS}, got {look!r}")
    if look == "taxel":
        _need(source, ("signals", "baseline"), skin, look)
        settings = _taxel_settings(source, spec, skin)
        baseline = np.asarray(source["baseline"])
        frames = source["signals"]
        attrs = {"settings": {k: list(v) if isinstance(v, tuple) else v for k, v in settings.items()}}
    else:
        _need(source, ("truth", "truth_reference") if look == "none" else
              ("truth", "raw", "raw_reference"), skin, look)
        frames = source["truth"] if look == "none" else source["raw"]
        params = segmentation_params(segmentation or {}, look) if look != "none" else {}
        attrs = {"segmentation": params} if params else {}
    n = len(frames)
    examples, shown = _example_frames(source, n), {}
    labels = [k for k in LABEL_KEYS if k in source]
    scores = []
    for start in tqdm(range(0, n, CHUNK), desc=f"markers[{skin}]", unit="chunk", disable=None,
                      leave=False):
        stop = min(start + CHUNK, n)
        chunk = np.asarray(frames[start:stop])
        if look == "none":
            images = chunk.astype(np.uint8, copy=True)
        elif look == "taxel":
            images = signal_to_marker(chunk, baseline, **settings)
        else:
            truth = np.asarray(source["truth"][start:stop])
            images = np.stack([segment(f, **params) for f in chunk])
            scores += [(iou(p, t), centroid_error(p, t)) for p, t in zip(images, truth)]
        for i in (i for i in examples if start <= i < stop):
            j = i - start
            shown[i] = [chunk[j], images[j], truth[j]] if look in POLARITY else [images[j]]
        yield {"images": images, **{k: np.asarray(source[k][start:stop]) for k in labels}}

    if look == "none":
        reference = np.asarray(source["truth_reference"]).astype(np.uint8)
    elif look == "taxel":
        reference = signal_to_marker(baseline, baseline, **settings)
    else:
        reference = segment(np.asarray(source["raw_reference"]), **params)
    if look in POLARITY:                       # a row per example: raw | segmented | truth
        rows = [shown[i] for i in examples] or [[reference]]
        sheet = contact_sheet([img for row in rows for img in row], cols=len(rows[0]))
    else:
        sheet = contact_sheet([reference] + [shown[i][0] for i in examples], cols=EXAMPLES + 1)
    out = {"reference": reference, "figures": {"examples": png(sheet)},
           "attrs": {"skin": skin, "look": look, "frames": int(n),
                     "image_size": list(reference.shape), **attrs}}
    if "indenters" in source:
        out["indenters"] = np.asarray(source["indenters"]).astype(str)
    if scores:
        s = np.asarray(scores, float)
        out["metrics"] = {f"segment/{skin}/iou": float(s[:, 0].mean()),
                          f"segment/{skin}/centroid_px": float(s[:, 1].mean())}
    return out


def no_contact_shots(deform: Mapping, patterns: Mapping, spec: Mapping, segmentation: Mapping,
                     shots, *, size=(128, 128), spp: int = 1, backend: str = "auto") -> list[np.ndarray]:
    """A camera skin's no-contact pad as marker images, one per shot (seed, frame index): the
    render node's Renderer on the deform artifact's pad (the skin's look, light, noise and
    upsample; one scene, the camera noise of a shot drawn from rng (seed, index + 1)),
    segmented as the markers node segments.  The shot (the skin's render seed, -1) is the
    markers node's reference; any other shot is another take of it under fresh camera noise."""
    from stages.markers.render import Renderer, marker_set
    from stages.markers.segment import segment

    look = spec.get("look", "none")
    if look not in POLARITY:
        raise ValueError(f"look {look!r} has no camera noise (gelsight, tactip)")
    params = segmentation_params(segmentation or {}, look)
    still = np.zeros(np.shape(deform["surface_z"]) + (3,), np.float32)
    r = Renderer(deform["grid_x"], deform["grid_y"], deform["surface_z"], deform["on_pad"],
                 marker_set(patterns, spec["pattern"]), look=look, size=size, spp=spp, backend=backend,
                 light=spec.get("light"), noise=float(spec.get("noise", 0.0)),
                 upsample=float(spec.get("upsample", 1.0)))
    out = []
    for seed, index in shots:
        r.seed = int(seed)
        out.append(segment(r.render(still, int(index))["raw"], **params))
    return out


def reference_takes(*, markers: Mapping, source: Mapping, deform: Mapping, patterns: Mapping, skin: str,
                    spec: Mapping, segmentation: Mapping, takes: int) -> dict:
    """Node `references[skin]`: `takes` more no-contact marker images of the skin, as its camera
    would give them on other days: the markers node's reference is one shot of a noisy camera,
    and every re-mount of a real sensor takes another, differing at a few marker-edge pixels.
    A force model trained against the one reference reads those pixels as force (GelSight's
    supervised model: 1.00-2.03x at 0.5-2 N over nine realisations, scripts/reference_noise.py);
    reading every training contact against each of these takes too, it learns to ignore them.

    source: the markers node's source (render[skin] for camera looks), whose attrs give the
    scene (size, spp, backend, noise seed; a store rendered with Dr.Jit's LLVM backend is shot
    with the scalar one where LLVM is missing, and reference_rendered_again_px then counts the
    pixels that changes).  Take k is that scene shot after the sequence:
    camera noise (seed, frames + k + 1), which no frame or reference uses.  Looks without
    camera noise (none, taxel) give no takes.  Returns `takes` (K,H,W) uint8 0/255,
    figures/takes (the reference and the first takes above the pixels where each differs
    from it, in red) and attrs (seed, pixels each take differs by, and how many pixels the
    reference shot renders differently from the markers node's reference: none when this
    backend made the store's renders)."""
    from stages.figures import contact_sheet, png
    from stages.markers.mitsuba_backend import resolve_backend

    reference = np.asarray(markers["reference"])
    look = spec.get("look", "none")
    if int(takes) < 0:
        raise ValueError(f"references[{skin}]: takes must be >= 0, got {takes}")
    attrs = {"skin": skin, "look": look, "takes": int(takes)}
    if look not in POLARITY or int(takes) == 0:
        attrs["why_none"] = ("no takes asked" if look in POLARITY else
                             f"look {look!r} has no camera noise: its reference is exact")
        return {"takes": np.zeros((0,) + reference.shape, np.uint8), "attrs": attrs}
    scene = dict(getattr(source, "attrs", {}) or {})
    missing = [k for k in ("seed", "spp", "backend", "size") if k not in scene]
    if missing:
        raise KeyError(f"references[{skin}]: the render's attrs lack {', '.join(missing)}")
    if list(scene["size"]) != list(reference.shape):
        raise ValueError(f"references[{skin}]: render size {list(scene['size'])} is not the "
                         f"reference's {list(reference.shape)}")
    seed, n = int(scene["seed"]), len(deform["displacement"])
    backend = resolve_backend("auto" if scene["backend"] == "llvm" else str(scene["backend"]))
    shots = [(seed, -1)] + [(seed, n + k) for k in range(int(takes))]
    again, *out = no_contact_shots(deform, patterns, spec, segmentation, shots, size=reference.shape,
                                   spp=int(scene["spp"]), backend=backend)
    out = np.stack(out).astype(np.uint8)
    attrs.update(seed=seed, backend=backend, frame_indices=[n + k for k in range(int(takes))],
                 pixels_differ=[int(v) for v in (out != reference[None]).sum(axis=(1, 2))],
                 reference_rendered_again_px=int((again != reference).sum()))
    shown = out[:4]
    top = [np.repeat(img[..., None], 3, 2) for img in [reference, *shown]]
    bottom = [np.full_like(top[0], 90)]
    for img in shown:
        d = np.repeat((reference // 3)[..., None], 3, 2)
        d[img != reference] = (255, 0, 0)
        bottom.append(d)
    return {"takes": out, "attrs": attrs,
            "figures": {"takes": png(contact_sheet(top + bottom, cols=len(top)))}}
