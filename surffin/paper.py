"""The numbers the paper (Frangez et al. 2021) reports, in one place.

surffin's results are set beside them by the calibration diagnostics
(:mod:`surffin.analysis.diagnostics`), the sensitivity analysis
(:mod:`surffin.analysis.sensitivity`), the paper comparison
(:mod:`surffin.analysis.reproduction`) and the calibration table of the report
(:mod:`surffin.report.figures`). They are quoted, never used as inputs of the
method. The variability of the calibration coefficients is in a gauge the
paper does not state (surffin fits in the gauge E = 1).
"""

__all__ = [
    "CITATION",
    "DOI",
    "MEAN_R2",
    "VARIABILITY_PERCENT",
    "CORRELATION",
    "WALL_FEATURE_STD",
    "REPEATABILITY_PERCENT",
    "CALIBRATION",
    "SLOPES",
    "SEPARATION_DEG",
    "FEATURE_SPAN_PERCENT",
    "ACCURACY",
    "RUNTIME_S",
    "RUNTIME_VIEWS",
]

#: The paper's DOI, and the reference every store gives in its CF attribute ``references``.
DOI = "10.1016/j.autcon.2021.103799"
CITATION = (
    "Frangez V., Salido-Monzú D., Wieser A. (2021): Surface finish classification using depth camera data. "
    f"Automation in Construction 129, 103799. https://doi.org/{DOI}"
)
#: Mean R^2 of the calibration fit over the image (section 3.3).
MEAN_R2 = 0.98
#: Variability in % of each calibration coefficient over the whole image (section 3.3, Table 2).
VARIABILITY_PERCENT = {"A": 8.94, "B": 3.92, "C": 1.79, "D": 1.38, "E": 4.44}
#: Correlation matrix of the calibration coefficients across pixels, rows and columns ``terms`` (Table 2).
CORRELATION = {
    "terms": ["A", "B", "C", "D", "E"],
    "matrix": [
        [1.0, 0.14, 0.16, -0.12, -0.16],
        [0.14, 1.0, 0.17, -0.14, -0.46],
        [0.16, 0.17, 1.0, -0.99, 0.09],
        [-0.12, -0.14, -0.99, 1.0, -0.13],
        [-0.16, -0.46, 0.09, -0.13, 1.0],
    ],
}
#: Standard deviation of the features R0 and n fitted on the calibration wall (section 3.3).
WALL_FEATURE_STD = {"R0": 0.005, "n": 0.008}
#: Repeatability in % of two calibrations: coefficients within 1 %, reflectance, R0 and n (section 3.3).
REPEATABILITY_PERCENT = {"coefficients": 1.0, "reflectance": 2.9, "R0": 0.5, "n": 1.4}
#: The calibration numbers above as the calibration diagnostics report them (section 3.3, Table 2).
CALIBRATION = {
    "mean_r2": MEAN_R2,
    "variability_percent": VARIABILITY_PERCENT,
    "correlation": CORRELATION,
    "wall_feature_std": WALL_FEATURE_STD,
    "repeatability_percent": REPEATABILITY_PERCENT,
}
#: K views: the standard deviation of R0 and n is proportional to K^slope (section 4, Fig. 12).
SLOPES = {"R0": -0.5, "n": -1.0}
#: Two views: separation (deg) from which R0 and n are within 10 % at the high reflectance noise (section 4, Fig. 11).
SEPARATION_DEG = 20.0
#: Span in % of R0 and n within a specimen, about (features, beside Fig. 14).
FEATURE_SPAN_PERCENT = {"R0": 10.0, "n": 4.0}
#: Accuracy of the k-NN labels and of the filtered labels of a scene (section 5.2).
ACCURACY = {"label": 0.97, "label_filtered": 1.0}
#: Time from raw files to labels, s: about 5 min for :data:`RUNTIME_VIEWS` views.
RUNTIME_S = 300.0
#: Views of the scene timed by :data:`RUNTIME_S`.
RUNTIME_VIEWS = 5
