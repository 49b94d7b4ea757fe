"""``usp_jax.config``: the public name of :mod:`usp_jax.training.config`, which config files
(``usp-jax train --config FILE.py``) and users import. Both names are one module object, so
every attribute a config file reaches through ``usp_jax.config`` stays where it was."""

import sys

from usp_jax.training import config as _config

sys.modules[__name__] = _config
