"""Tree parameters from ground-based and fused clouds (System B, paper section 4.3).

Steps, each a module of small functions with a frozen parameter dataclass:

* :mod:`.stems` - stem detection at breast height, DBH by circle fitting, stem curves;
* :mod:`.segmentation` - every point assigned to a tree, grown from the stems upward;
* :mod:`.leafwood` - unsupervised leaf-wood separation by multi-scale covariance features;
* :mod:`.qsm` - TreeQSM-like cylinder models (cover sets, segments, fitted cylinders);
* :mod:`.crown` - height, crown base, crown widths, area and volume;
* :mod:`.evaluate` - comparison with field records (R2, RMSE, rRMSE).
"""
