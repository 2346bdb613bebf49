"""FevarPlanner core: 3D catheter path planning for FEVAR from a pre-operative CT and one
intra-operative fluoroscopic frame (Zheng et al., ICRA 2019).

Pure Python (numpy, scipy, scikit-image, SimpleITK, VTK, torch); it never imports Slicer or
Qt. One module per pipeline stage, data flowing one way:
io -> segmentation -> skeleton -> graph -> matching -> deformation -> planning -> export,
with projection (the C-arm geometry, eq. 1), phantom (synthetic cases with ground truth),
baselines (ICP-TPS, rigid), evaluation (the paper's metrics) and cli beside them.
"""

__version__ = "0.1.0"

#: Said by the CLI (--help, --version), the Slicer module's help and the README.
RESEARCH_USE_STATEMENT = (
    "FevarPlanner is research software. It is not a medical device, has not been cleared or approved "
    "by any regulator, and must not be used for diagnosis, treatment or any clinical decision.")
