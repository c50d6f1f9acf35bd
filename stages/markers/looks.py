"""Camera looks of marker skins: materials, LED rigs and the shading of ray-traced samples.

A look shades the samples of one ray-tracing pass (stages.markers.render) from what the
surface is at each sample: marker coverage, unit normal and position.  Lambert diffuse plus a
Blinn-Phong lobe (the reflective coating of a GelSight gel) under point LEDs evenly on a ring
around the optical axis; every LED counts exactly in every sample, so the image has no
light-sampling noise - only the camera noise added on purpose.

  gelsight  grey gel (albedo 0.6) with dark markers, three LEDs low at the sides (25 deg
            elevation), red, green, blue by default, so indentation slopes tint the image
  tactip    white pin tips on a black dome, six white LEDs around the lens (soft, frontal)
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

GAMMA = 2.2


@dataclass(frozen=True)
class Look:
    """Materials and LED ring of a camera look."""
    skin_albedo: float
    marker_albedo: float
    ambient: float               # stray light, fraction of the LEDs' summed colour
    specular: float              # Blinn-Phong weight (the gel's reflective coating)
    shininess: float
    ring_radius: float           # LED ring radius, fraction of the larger pad side
    ring_elevation_deg: float    # LED elevation seen from the pad centre (90: on the axis)
    exposure: float              # linear level of the unmarked (gelsight) / marked (tactip) pad centre
    light: tuple                 # default LED colours (relative RGB strengths)


LOOKS = {
    "gelsight": Look(skin_albedo=0.6, marker_albedo=0.05, ambient=0.08, specular=0.25,
                     shininess=30.0, ring_radius=2.0, ring_elevation_deg=25.0, exposure=0.4,
                     light=((1.0, 0.12, 0.12), (0.12, 1.0, 0.12), (0.12, 0.12, 1.0))),
    "tactip": Look(skin_albedo=0.004, marker_albedo=0.9, ambient=0.1, specular=0.0,
                   shininess=1.0, ring_radius=0.25, ring_elevation_deg=80.0, exposure=0.75,
                   light=((1.0, 1.0, 1.0),) * 6),
}


class LedRig:
    """Point LEDs evenly on a ring around the optical axis, the first towards -y (image top).

    light: one RGB per LED, its relative strength: each LED is scaled so that it lights the
    undeformed pad centre (normal -z) with that colour whatever the ring's size, and the
    camera's exposure puts the pad centre's brighter material at look.exposure (linear,
    brightest channel), so any light list gives a well exposed image.
    """

    def __init__(self, look: Look, light, pad_size_mm, centre):
        colours = np.asarray(light, float)
        if colours.ndim != 2 or colours.shape[1] != 3 or not len(colours):
            raise ValueError(f"render light {light!r}: expected a list of RGB triples, one per LED")
        radius = look.ring_radius * max(pad_size_mm)
        height = radius * np.tan(np.radians(look.ring_elevation_deg))
        azimuth = -np.pi / 2 + 2 * np.pi * np.arange(len(colours)) / len(colours)
        offset = np.stack([radius * np.cos(azimuth), radius * np.sin(azimuth),
                           np.full(len(colours), -height)], -1)
        self.position = (np.asarray(centre, float) + offset).astype(np.float32)
        dist2 = (offset ** 2).sum(1)                             # to the pad centre
        cos0 = height / np.sqrt(dist2)                           # incidence at the centre
        self.gain = (colours * (dist2 / cos0)[:, None]).astype(np.float32)
        self.dist2 = dist2.astype(np.float32)
        self.ambient = (look.ambient * colours.sum(0)).astype(np.float32)
        centre_radiance = max(look.skin_albedo, look.marker_albedo) * (1 + look.ambient) * colours.sum(0)
        if centre_radiance.max() <= 0:
            raise ValueError(f"render light {light!r}: the LEDs give no light")
        self.exposure = np.float32(look.exposure / centre_radiance.max())
        self.colour = colours.astype(np.float32)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot product of channel-first vector images (3, h, w)."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def shade(look: Look, rig: LedRig, normal: np.ndarray, position: np.ndarray,
          coverage: np.ndarray, eye) -> np.ndarray:
    """Linear RGB radiance (3, h, w) of samples with channel-first unit normals and positions
    (3, h, w) and marker coverage (h, w) in [0, 1], seen from the camera at `eye`."""
    albedo = look.skin_albedo + (look.marker_albedo - look.skin_albedo) * coverage
    view = np.asarray(eye, np.float32)[:, None, None] - position
    view /= np.sqrt(_dot(view, view))
    irradiance = np.empty((3,) + coverage.shape, np.float32)
    irradiance[:] = rig.ambient[:, None, None]
    gloss = np.zeros_like(irradiance)
    for led, gain, colour, d0 in zip(rig.position, rig.gain, rig.colour, rig.dist2):
        to_led = led[:, None, None] - position
        d2 = _dot(to_led, to_led)
        to_led /= np.sqrt(d2)
        irradiance += gain[:, None, None] * (np.maximum(_dot(normal, to_led), 0) / d2)
        if look.specular:
            half = to_led + view
            cos_h = np.maximum(_dot(normal, half), 0) / np.sqrt(_dot(half, half))
            gloss += colour[:, None, None] * (cos_h ** look.shininess * (d0 / d2))
    return (albedo * irradiance + look.specular * (1 - coverage) * gloss) * rig.exposure


def camera_image(linear: np.ndarray, noise: float, rng: np.random.Generator | None) -> np.ndarray:
    """uint8 image from linear radiance (..., 3): clip, sRGB-like gamma, Gaussian noise of
    sigma `noise` grey levels (none when noise is 0)."""
    img = 255.0 * np.clip(linear, 0, 1) ** np.float32(1 / GAMMA)
    if noise > 0:
        img += noise * rng.standard_normal(img.shape, dtype=np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
