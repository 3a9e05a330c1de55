"""A study spec: the YAML file loaded, checked and turned into a frozen ``StudySpec``.

The lowest layer of ``sweeper``: it imports ``agent.config`` and ``encoders.options`` (no
torch) and nothing else of ``sweeper``. Private modules: ``_yaml`` (the YAML 1.2 loader and
``SpecError``), ``_models`` (the pydantic models, ``load_spec``, the halving defaults),
``_space`` (search spaces derived from the hyperparameter declarations, per-method
variants and SAC fields), ``_sampling`` (configurations sampled from a space),
``_errors`` (validation errors as one line with the field's dotted path), ``_words``
(wording every message shares: ``plural``, the help formatter).
"""

from sweeper.spec._errors import suggest
from sweeper.spec._models import (
    DEFAULT_KEEP,
    DEFAULT_RUNG_FRACTIONS,
    Execution,
    StudySpec,
    check_files,
    default_rungs,
    load_spec,
    parse_spec,
    positive_int,
    rungs_at,
)
from sweeper.spec._sampling import derive_rng, param_value, sample_configs
from sweeper.spec._space import parse_method
from sweeper.spec._words import HelpFormatter, plural
from sweeper.spec._yaml import SpecError

__all__ = [
    "DEFAULT_KEEP",
    "DEFAULT_RUNG_FRACTIONS",
    "Execution",
    "HelpFormatter",
    "SpecError",
    "StudySpec",
    "check_files",
    "default_rungs",
    "derive_rng",
    "load_spec",
    "param_value",
    "parse_method",
    "parse_spec",
    "plural",
    "positive_int",
    "rungs_at",
    "sample_configs",
    "suggest",
]
