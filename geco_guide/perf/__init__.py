"""Performance: the cost model of a guided run, stage profiling, full-size model builders."""

__all__: list[str] = []
