"""The package's ranking statistics, importable by the tests as ``ranking``."""

from geco_guide.ranking import average_precision, best_threshold_iou_f1, spearman

__all__ = ["average_precision", "best_threshold_iou_f1", "spearman"]
