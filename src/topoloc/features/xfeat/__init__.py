"""XFeat (Potje et al., CVPR 2024): its network, the runtimes that run it and the sparse inference after it.

* :mod:`~topoloc.features.xfeat.runtimes`: one small class per runtime (ONNX
  Runtime, the default; PyTorch from the ``learned`` extra), the shipped network
  files and their checks;
* :mod:`~topoloc.features.xfeat.postprocess`: heatmap, non-maximum suppression,
  top-k, sampling and normalisation in NumPy/OpenCV, shared by every runtime;
* :mod:`~topoloc.features.xfeat.network`: the network as a PyTorch module
  (imports PyTorch; the PyTorch runtime and the ONNX export only).

:mod:`topoloc.features.learned` is what the rest of the package calls.
"""
