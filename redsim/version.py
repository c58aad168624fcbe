"""The package version, written once here (``redsim.__version__``; pyproject.toml reads it: ``dynamic = ["version"]``).

A module of its own so the engine and the trainers can record it without importing the ``redsim``
package (whose ``__init__`` registers the envs: that edge would close an import circle).
"""

from __future__ import annotations

__version__ = "0.1.0"

__all__ = ["__version__"]
