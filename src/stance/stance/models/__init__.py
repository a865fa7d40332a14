"""Programmatic robot models (Pinocchio models built in code, no URDF)."""

from .mannequin import MANNEQUIN_LIMIT_FILE, build_mannequin

__all__ = ["MANNEQUIN_LIMIT_FILE", "build_mannequin"]
