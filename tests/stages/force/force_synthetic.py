"""Synthetic contact sequences for the force-regressor tests: a disc whose radius encodes the
normal force and whose position encodes the shear force, pressed and released."""
import numpy as np

TINY = {"input_size": 16, "stem_channels": 4, "encoder_channels": [8], "hidden": 8,
        "head_channels": [16, 16]}


def blob_contacts(n: int, length: int = 14, size: int = 32, seed: int = 0):
    """n contacts of `length` frames: (images list of (T,size,size) uint8, forces list of (T,3))."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size] + 0.5
    images, forces = [], []
    for _ in range(n):
        t = np.sin(np.pi * np.linspace(0.0, 1.0, length + 2)[1:-1])       # press, then release
        x0, y0 = rng.uniform(0.35 * size, 0.65 * size, 2)
        dx, dy = rng.uniform(-0.12 * size, 0.12 * size, 2)
        r = rng.uniform(0.12, 0.28) * size * t
        x, y = x0 + dx * t, y0 + dy * t
        img = ((xx[None] - x[:, None, None]) ** 2 + (yy[None] - y[:, None, None]) ** 2
               <= r[:, None, None] ** 2).astype(np.uint8) * 255
        force = np.stack([0.25 * (x - size / 2), 0.25 * (y - size / 2), -1.5 * r], 1)
        images.append(img)
        forces.append(force.astype(np.float32))
    return images, forces


def contact_artifact(images, forces, indenter_names, size=32):
    """A contact-sequence artifact as a plain dict, contact k pressed by indenter_names[k]."""
    names = sorted(set(indenter_names))
    n = [len(f) for f in forces]
    force = np.concatenate(forces)
    depth = np.abs(force[:, 2]) / 12.0
    phase = np.concatenate([np.where(np.arange(k) < k // 2, 0, 3) for k in n]).astype(np.int8)
    # every third frame of a contact is location-paired (M2M's fine-tune and genforce_plus read those)
    paired = np.concatenate([np.arange(k) % 3 == 1 for k in n])
    return {"images": np.concatenate(images), "reference": np.zeros((size, size), np.uint8),
            "force": force, "normalised_depth": depth.astype(np.float32), "phase": phase, "paired": paired,
            "contact_id": np.repeat(np.arange(len(n)), n).astype(np.int32),
            "indenter_id": np.repeat([names.index(s) for s in indenter_names], n).astype(np.int16),
            "frame": np.arange(sum(n)), "indenters": np.asarray(names, object)}
