"""ago_runtime.scoring: numbers that judge a prediction - the Occ3D metric and ranking metrics.

Holds `metric` (OccupancyMetric: the Occ3D confusion matrix, IoU, mIoU; upsample_nearest),
`ranking` (average precision, ROC AUC) and `cli` (`ago metric`).

May import: numpy and ago_runtime's basics; `cli` may also import formats and typer.
"""
