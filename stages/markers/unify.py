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

from stages.common import LABEL_KEYS, check_option
from stages.markers.uskin import USKIN_PAD_MM, signal_to_marker

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
    check_option(f"sensors.{skin}.look", look, LOOKS)
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
