"""The recalibration map the default model carries: candidate C (docs/MODEL.md C.7, "The default map";
docs/VALIDATION.md, "A map that keeps the order (candidate C, centred isotonic regression)").

Centred isotonic regression of the physical topple frequency on the default model's P(topple)
(counted and smoothed, C.12), fitted on the corpus's drawn pushes (data/logs/corpus_all, 2,253
pushes on 189 corpus objects; no held-out object was used): 6-fold cross-validation grouped by
object gave held-out Brier 0.1259 against the identity's 0.1349.  It replaced candidate R (the
isotonic map of the same fit, reports/recalibrated_sp.toml) by a rule written down before it
was played.  Regenerate with ``toppledb recalibrate data/logs/corpus_all --folds 6 --seed 0
--methods centred`` (reports/recalibrated_centred.toml is that output).  The values are the
fitter's, unrounded, so the default reproduces the reports exactly.
"""

RECALIBRATION_X = (
    0.0, 0.00038461538461531664, 0.000709765036550712, 0.0011182795698924538, 0.0014468864468864528,
    0.0017151798736022876, 0.005139265996455408, 0.013018090569561144, 0.036387310149729825,
    0.06624999999999992, 0.1145128553429195, 0.15820709052851903, 0.2193155148516876,
    0.2817291666666667, 0.3081532859048514, 0.33742611513066056, 0.359186387521209,
    0.3832638888888889, 0.4048496549476694, 0.44474661004650506, 0.49054046558208075,
    0.5556081388960603, 0.603199591736177, 0.6295235277542971, 0.6398077755577756,
    0.6529532079032078, 0.6871873104428252, 0.7164555127412269, 0.7611821469129161,
    0.8109716394716395, 0.893034126984127, 0.9677777777777777, 1.0
)
"""Knots x_k, strictly increasing in [0, 1]."""

RECALIBRATION_Y = (
    0.0, 0.0, 0.0, 0.0032258064516129032, 0.016666666666666666, 0.05454545454545456,
    0.07039473684210527, 0.07941176470588235, 0.1392857142857143, 0.2, 0.2080536912751678,
    0.22857142857142856, 0.3338983050847457, 0.375, 0.3943820224719101, 0.4, 0.4714285714285714,
    0.4764705882352942, 0.5211538461538461, 0.6071428571428572, 0.69, 0.7033707865168539,
    0.7463414634146341, 0.7846153846153846, 0.8222222222222222, 0.88, 0.895, 0.9071428571428571,
    0.9615384615384616, 0.9727272727272728, 1.0, 1.0, 1.0
)
"""Knots g(x_k), non-decreasing in [0, 1]."""
