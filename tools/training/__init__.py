"""Segmentation network training: simulator-rendered data (``segdata``), the network and its ONNX
export (``training``, needs the ``train`` extra), post-hoc logit adjustment (``logit_adjust``)."""
