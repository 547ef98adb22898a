"""lazyq-jax: lazy action value models for Q-learning (Schubert & Toussaint, 2020) in JAX."""

from lazyq_jax.types import Transitions

__all__ = ["Transitions"]
