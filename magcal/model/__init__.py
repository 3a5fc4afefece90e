"""The model: effect terms (:class:`~magcal.model.terms.Effect`, the :data:`~magcal.model.terms.EFFECTS`
registry, :class:`~magcal.model.terms.Model`), the built-in catalogue, the simulator's perturbations, a user's own
effects, and what total-field data can determine.

Importing any module of this package fills the catalogue (:mod:`magcal.model.effects` registers at import).
"""

from magcal.model import effects  # noqa: F401  (registers the built-in catalogue)
from magcal.model.terms import BASE_TERMS, EFFECTS, Context, Domain, Effect, Model, parse_effect, register, term_label

__all__ = ["EFFECTS", "BASE_TERMS", "Context", "Domain", "Effect", "Model", "parse_effect", "register", "term_label"]
