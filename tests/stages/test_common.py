"""stages.common: the timing split every training node uses."""
from stages.common import split_timing


def test_split_timing_moves_only_timings_at_every_depth():
    history = {"loss": [3.0, 2.0], "seconds": 4.5, "steps": 2,
               "genforce": {"pretrain": {"loss": [1.0], "frames_per_s": 80.0, "contacts": 9},
                            "finetune": {"loss": [0.5]}}}
    kept, timing = split_timing(history)
    assert kept == {"loss": [3.0, 2.0], "steps": 2,
                    "genforce": {"pretrain": {"loss": [1.0], "contacts": 9}, "finetune": {"loss": [0.5]}}}
    assert timing == {"seconds": 4.5, "genforce": {"pretrain": {"frames_per_s": 80.0}}}
    assert history["seconds"] == 4.5                                   # the input is left alone
