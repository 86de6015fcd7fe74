"""Source data: the Transitions type, loaders for Minari ids and D4RL-format files, collection."""

from hipode_pipeline.data.transitions import SourceInfo, Transitions

__all__ = ["SourceInfo", "Transitions"]
