"""The package's ranking statistics, importable by the tests as ``ranking``."""

from geco_guide.ranking import average_precision, spearman

__all__ = ["average_precision", "spearman"]
