"""Measures of an answer: accuracy metrics (``metrics``), the lip-sliding paper's lip-shape
analysis (``lip_shape``), distances between surfaces (``surface_distance``) and mirror symmetry
(``symmetry``)."""
