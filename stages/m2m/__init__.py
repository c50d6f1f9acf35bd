"""Marker-to-marker (M2M) translation: one image-conditioned generator for every sensor pair.

Modules: `data` (paired training frames, the shared evaluation-frame selection; numpy only),
`model` (the UNet, diffusion samplers, weights as arrays, `load_translator`), `train`
(batches, loss, optimiser loop), `flow` (the training-free flow-warp baseline), `nodes`
(the pipeline's node functions).  Importing this package imports no torch.
"""
from stages.m2m.data import eval_frame_indices

__all__ = ["eval_frame_indices", "load_translator"]


def load_translator(model):
    """A Translator from an M2M model artifact (see stages.m2m.model.load_translator)."""
    from stages.m2m.model import load_translator as _load
    return _load(model)
