"""What the benchmarks record about the machine they ran on: the package's own helpers, which
`hipode sweep` uses too (kept importable here as `from machine import ...`)."""

from hipode_pipeline.machine import LoadSampler, cpu_name, load_average

__all__ = ["LoadSampler", "cpu_name", "load_average"]
