"""The maps of P(topple) the default model carries: the recalibration map (docs/MODEL.md C.7,
"The default map"; docs/VALIDATION.md, candidates C, S and T) the down map (C.15, candidates D and G_down) and the side map (C.16).

Centred isotonic regression of the physical topple frequency on the default model's P(topple)
(its corrections, stuck_finger and tip_path included, counted and smoothed as C.12 says), fitted on the
corpus's drawn pushes (data/logs/corpus_all, 2,253 pushes on 189 corpus objects, push player
version 5; no held-out object was used): 6-fold cross-validation grouped by object gave
held-out Brier 0.1174 against the identity's 0.1258.  It belongs to the default's corrections and noise: a model with others
needs its own fit.  Regenerate with ``toppledb recalibrate data/logs/corpus_all --folds 6
--seed 0 --methods centred`` (reports/recalibrated_centred.toml is that output; ``--down`` on the
same log fits the same knots, reports/recalibrated_down.toml).  The down map and the side map below
say where theirs come from.  The values
are the fitter's, unrounded, so the default reproduces the reports exactly.
"""

RECALIBRATION_X = (
    0.0, 0.0003448275862067973, 0.000515702385098867, 0.0010915712254721249, 0.001564625850340102,
    0.0018181818181818299, 0.002379412325082914, 0.0036454761594512546, 0.006035576782315903,
    0.01677882131276568, 0.05805841105103271, 0.10556487633813214, 0.11683411656673692,
    0.12062424969987993, 0.12704067909214967, 0.15177337567611632, 0.18009523809523806,
    0.18700255102040814, 0.2103818393701206, 0.25487393124893126, 0.2831547619047619,
    0.3013997228405123, 0.32350056887556883, 0.3308632478632479, 0.33648735986235984,
    0.36037710182537774, 0.3877193917193917, 0.3967151539662982, 0.4108619682484062,
    0.4422210925624084, 0.48211873012277884, 0.560158885937489, 0.6181944444444444,
    0.6385362499819022, 0.6741853091081033, 0.6919506037943539, 0.7155773897262867,
    0.7578616829598971, 0.8073736263736263, 0.8831931216931217, 0.9677777777777777, 1.0
)
"""Knots x_k, strictly increasing in [0, 1]."""

RECALIBRATION_Y = (
    0.0, 0.0, 0.0, 0.0058823529411764705, 0.02857142857142857, 0.05, 0.054838709677419356,
    0.06428571428571428, 0.09285714285714286, 0.11779661016949153, 0.12773722627737227,
    0.15348837209302327, 0.18181818181818182, 0.18571428571428572, 0.2235294117647059,
    0.22575757575757577, 0.24444444444444444, 0.2857142857142857, 0.29375, 0.2986486486486486,
    0.3142857142857143, 0.34545454545454546, 0.39090909090909093, 0.42, 0.45, 0.4724137931034483,
    0.57, 0.5739130434782609, 0.6407407407407407, 0.6479999999999999, 0.6923076923076923,
    0.7047120418848167, 0.75, 0.8065217391304348, 0.8583333333333333, 0.8625, 0.86875,
    0.8964285714285715, 0.98125, 1.0, 1.0, 1.0
)
"""Knots g(x_k), non-decreasing in [0, 1]."""

# The down map (docs/MODEL.md C.15; docs/VALIDATION.md, candidates D and G_down): logistic weights,
# in the order of ``feature_map.DOWN_FEATURES``, for the pushes with u_z < -0.3, fitted on the
# unmapped P of the 3,828 such pushes of two corpus logs (data/logs/corpus_all and corpus_s1, all
# 189 corpus objects).  Cross-validated (6 folds by object, seed 0) on those pushes: held-out Brier
# 0.1255 against the centred map's 0.1403.  Regenerate with ``toppledb recalibrate
# data/logs/corpus_all data/logs/corpus_s1 --folds 6 --seed 0 --down`` and take its ``down_map``
# (the knots above stay: the down map reads P before them; reports/recalibrated_down_more.toml).
DOWN_MAP = (
    3.163041594904531, 0.49427114045238457, 0.19258911468034423, 0.46109132111805856,
    -1.3065967520453632, -0.18426266743449735, -2.5616056325723697, 0.09607021387304948,
)

# The side map (docs/MODEL.md C.16; docs/VALIDATION.md, "Side pushes sharpened along the force they
# need"): logistic weights, in the order of ``feature_map.SIDE_FEATURES``, for the pushes with
# -0.3 <= u_z < 0.3 and 0.05 < P < 0.95, fitted on the default's P (C.7 applied) of the corpus log's
# 137 such pushes.  Cross-validated (6 folds by object, seed 0): held-out Brier on them 0.1427
# against 0.1537 without it.  Regenerate with ``toppledb recalibrate data/logs/corpus --folds 6
# --seed 0 --side`` (reports/recalibrated_side.toml).
SIDE_MAP = (-3.259649988432783, 0.8517342133875055, -2.2118633991662784)
