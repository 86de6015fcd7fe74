"""HIPODE's generators: one CVAE class (state transition, inverse action, inverse reward),
the value estimator with negative sampling and the forward dynamics ensemble."""

from hipode_pipeline.models.cvae import CVAE
from hipode_pipeline.models.dynamics import DynamicsEnsemble
from hipode_pipeline.models.generators import GeneratorConfig, Generators, train_generators
from hipode_pipeline.models.value import ValueEstimator

__all__ = [
    "CVAE",
    "DynamicsEnsemble",
    "GeneratorConfig",
    "Generators",
    "ValueEstimator",
    "train_generators",
]
