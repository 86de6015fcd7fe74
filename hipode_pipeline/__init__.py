"""HIPODE: policy-decoupled, high-return data augmentation for offline RL."""

__version__ = "0.1.0"
