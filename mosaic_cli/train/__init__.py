"""``mosaic train``: unsupervised training of the homography network from raw clips.

:mod:`.config` (what defines a run), :mod:`.data` (clips -> frame cache -> windows),
:mod:`.objective` and :mod:`.losses` (what each variant minimises),
:mod:`.schedule` (learning rate), :mod:`.run` (run folder, checkpoints, log),
:mod:`.distributed` (torchrun / DDP), :mod:`.validate` (MACE on --val flights) and
:mod:`.loop` (the procedure, top to bottom).
"""
