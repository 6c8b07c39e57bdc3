"""The configuration reference ``docs/configuration.md``, generated from the Config classes.

``soc-opt config-doc --out docs/configuration.md`` (or :func:`render`) writes it: the TOML layout
of a run configuration, then one section per :class:`~soc_opt.config.Config` class with its
docstring and a table of every field (key, type, default).  The run configuration's tables are
found by walking :class:`~soc_opt.methods.config.DPSOCConfig`'s nested configs and the plug-in tables of
the registered methods and estimators (:mod:`soc_opt.plugins`), so a sub-config added there or a plug-in's
own settings appear here without editing this module; library-only configs are listed in :data:`LIBRARY`.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import types
import typing
from typing import Any

from .config import PLUGIN_TABLES, Config, plugin_settings

__all__ = ["LIBRARY", "config_tables", "describe", "render"]

#: Configs that are not part of the run configuration: (public path, where they are used).
LIBRARY = (
    ("soc_opt.lqg.KLStepConfig", "library: `lqg.kl_step(config=...)`, `lqg.adapt_multiplier(config=...)`"),
    ("soc_opt.mstep.MStepConstraints", "library: `mstep.maximize(constraints=...)`"),
)


def resolve_config_class(path: str) -> type:
    """The class named by a dotted path such as ``"soc_opt.lqg.KLStepConfig"``."""
    module, _, name = path.rpartition(".")
    return getattr(importlib.import_module(module), name)


def _public_path(cls: type) -> str:
    """The shortest ``soc_opt.<module>`` path that exports ``cls`` (packages re-export their classes)."""
    parts = cls.__module__.split(".")
    for i in range(2, len(parts) + 1):
        module = importlib.import_module(".".join(parts[:i]))
        if getattr(module, cls.__name__, None) is cls:
            return f"{'.'.join(parts[:i])}.{cls.__name__}"
    return f"{cls.__module__}.{cls.__qualname__}"


def config_tables(root: type[Config], prefix: str = "") -> list[tuple[str, type[Config]]]:
    """``(TOML table, class)`` of ``root``, of every nested Config field and of every registered plug-in
    table of ``root`` (after the fields), depth first."""
    out = [(prefix, root)]
    hints = typing.get_type_hints(root)
    nested = [(f.name, hints[f.name]) for f in dataclasses.fields(root)] + list(plugin_settings(root).items())
    for name, tp in nested:
        if isinstance(tp, type) and issubclass(tp, Config):
            out += config_tables(tp, f"{prefix}.{name}" if prefix else name)
    return out


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin is typing.Literal:
        return " \\| ".join(f'"{a}"' if isinstance(a, str) else repr(a) for a in args)
    if origin in (typing.Union, types.UnionType):
        return " \\| ".join(_type_name(a) for a in args)
    if origin in (tuple, list):
        if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
            return f"list of {_type_name(args[0])}"
        return "list" if not args else f"list of {', '.join(_type_name(a) for a in args)}"
    if origin is dict:
        return "table"
    if tp is type(None):
        return "none"
    if isinstance(tp, type) and issubclass(tp, Config):
        return f"table ({tp.__name__})"
    return getattr(tp, "__name__", str(tp))


def _toml_value(v: Any) -> str:
    if v is None:
        return "(unset)"
    if isinstance(v, Config):
        return "(table)"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, (tuple, list)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + "}"
    return repr(v)


def _default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None


def describe(cls: type[Config], where: str) -> str:
    """One Markdown section: heading, docstring(s), and the table of fields with type and default."""
    lines = [f"## `{_public_path(cls)}` — {where}", ""]
    lines += ["```text", inspect.cleandoc(cls.__doc__ or ""), "```", ""]
    bases = [b for b in cls.__mro__[1:-1] if issubclass(b, Config) and b is not Config]
    if bases:
        lines += [f"The fields are documented with `{_public_path(bases[0])}`.", ""]
    hints = typing.get_type_hints(cls)
    lines += ["| key | type | default |", "|---|---|---|"]
    for f in dataclasses.fields(cls):
        if f.init and f.name != PLUGIN_TABLES:
            lines.append(f"| `{f.name}` | {_type_name(hints[f.name])} | `{_toml_value(_default(f))}` |")
    for name, tp in plugin_settings(cls).items():
        kind = cls.plugin_registry().kind
        lines.append(f"| `{name}` | {_type_name(tp)}, settings of the {kind} `{name}` | `(table)` |")
    return "\n".join(lines) + "\n"


_INTRO = """\
# Configuration

<!-- Generated by `soc-opt config-doc --out docs/configuration.md` (soc_opt/config_doc.py) from the
classes' docstrings, types and defaults; regenerate it instead of editing it. -->

Every algorithm keeps its solver choice, tolerances and hyperparameters in one frozen
dataclass (`soc_opt.config.Config`). Each is loadable from TOML with strict checking: an
unknown key or a value of the wrong type is rejected with a message naming the key, before any
simulation starts (`soc_opt.config.ConfigError`; the CLI exits with status 2).

The run configuration `soc_opt.methods.config.DPSOCConfig` holds every sub-configuration of a run;
an algorithm configuration file for `soc-opt run|compare TASK --config FILE` has this layout
(any table or key may be left out; every key is listed below):

```toml
i_switch = {i_switch}              # DPSOC-EM: EM phase after this many baseline iterations

[baseline]                # LQR-FLM (also the baseline part of DPSOC-EM)
iterations = {iterations}
samples = {samples}
kl_budget = 0.5

[baseline.fit]            # dynamics fitting (docs/math.md §2)
prior = "mixture"
n_components = 20

[baseline.kl]             # KL-step solver options (docs/math.md §6)
kl_rtol = 1e-6

[baseline.step_size]      # the GPS rule on the KL-budget multiplier (docs/math.md §6)
factor_min = 0.1
factor_max = 5.0
mult_max = 10000.0

[em]                      # EM phase (docs/math.md §3-§5)
n_em = 1
y_mode = "model"
cov_floor_scale = 0.5

[em.mstep]                # M-step solver tolerances (docs/math.md §5)
solver = "CLARABEL"

[evaluation]              # final-policy evaluation of `soc-opt compare`
seed_offset = 10000

[ilqg]                    # model-based iLQG (`soc-opt run TASK --method ilqg`)
iterations = 20
mu_init = 1e-6
```

Each method reads only its own sections of the shared file and ignores the others: LQR-FLM
reads `[baseline]`; DPSOC-EM `i_switch`, `[baseline]` and `[em]` (and only DPSOC-EM requires
`i_switch < baseline.iterations`); iLQG reads `[ilqg]`; `soc-opt compare` also reads
`[evaluation]`.  Every number must be finite: NaN and infinities are rejected with the key's name.
A run directory remembers the sections its method reads and refuses to resume with different ones.

Precedence (`soc_opt.experiments.run.load_run_config`, used by the CLI): the task's default file
`problems/experiments/<task>.toml` (if any), replaced by `--config FILE` when given; then
`--paper` (the paper scale `soc_opt.methods.config.PAPER`: {iterations} iterations, {samples} samples,
switch at {i_switch}), then the flags `--iterations`, `--samples`, `--workers`, `--i-switch`
(for `--method ilqg` only `--iterations`, which sets `ilqg.iterations`).

The initial policy covariance `Sigma = init_var * I`: `[baseline] init_var` of the run
configuration (the `--config` file, or the task's default file) when it sets one, else the task
file's own `init_var` (docs/tasks.md; default 1.0).  `config.json` of a run directory records the
value used.  In a sweep, `task.init_var` wins over the run-configuration file (docs/sweeps.md).

Task configurations (model, horizon, state, cost terms, noise, metric) are described in
`docs/tasks.md`.

The reference below is generated from the classes' docstrings, types and defaults.
"""


def render() -> str:
    """The full text of ``docs/configuration.md``."""
    from .methods.config import PAPER, DPSOCConfig

    sections = [_INTRO.format(**PAPER._asdict())]
    for table, cls in config_tables(DPSOCConfig):
        where = f"`[{table}]`" if table else "top level of an algorithm TOML (`--config`)"
        sections.append(describe(cls, where))
    for path, where in LIBRARY:
        sections.append(describe(resolve_config_class(path), where))
    return "\n".join(sections)
