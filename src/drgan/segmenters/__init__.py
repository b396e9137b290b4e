"""The segmenters that `drgan.segment` trains: U-Nets on generated (or real) image/mask pairs, and what evaluate and
analyze need to run them on real images.

Data flow: pairs.py (pairs -> random crops) -> module.py (SegmenterModule: U-Net, Dice + CE) ->
inference.py (sliding window over a full image -> class map 0 background / 1 particle / 2 contour).
registry.py: the allow-list of segmenter classes that configs build and checkpoints may name; predictors.py: the one
way from a checkpoint or a folder of predicted masks (e.g. nnU-Net's) to class maps, for evaluate and analyze.
"""
