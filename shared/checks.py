"""Range checks for SI parameters: declared constraints for the parameter dataclasses, and the
plain-function checks (``NAME must be a finite number > 0``) for functions that take them.

The parameter and configuration classes (``LocalModelParams``, ``BalloonParams``,
``DeviceLimits``, ...) are pydantic dataclasses (:func:`params_dataclass`) whose fields carry
their bounds as :data:`PositiveFinite`, :data:`NonNegFinite`, ... (a JSON Schema of each is
``pydantic.TypeAdapter(Cls).json_schema()``). They are strict (an int is a float, but a bool or a
string is not a number; NaN and inf are refused unless a field says otherwise) and refuse unknown
keyword arguments. A bad value raises :class:`pydantic.ValidationError`, a ValueError whose message
names the class, the field (also when the value was passed by position), the bound and the value
given; :func:`describe` puts its first problem on one line for command-line and file input.

The functions :func:`positive`, :func:`nonneg` and :func:`whole` check one argument of a plain
function; each returns the value as a float (int) so a caller can check and convert in one step.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Mapping
from typing import Annotated, Any, TypeVar, cast, dataclass_transform

import pydantic.dataclasses
from pydantic import ConfigDict, Field, Strict, ValidationError, model_validator
from pydantic_core import ArgsKwargs

#: Configuration of every parameter dataclass: strict types (an int or a numpy scalar is accepted
#: for a float, but not a bool or a string; a float is not an int), NaN and inf refused unless a
#: field allows them, and unknown keyword arguments refused (pydantic ignores them by default).
PARAMS_CONFIG = ConfigDict(strict=True, extra="forbid", allow_inf_nan=False)

#: A finite number (a bool is not one).
FiniteFloat = Annotated[float, Strict(), Field(allow_inf_nan=False)]
#: A finite number > 0.
PositiveFinite = Annotated[float, Strict(), Field(gt=0, allow_inf_nan=False)]
#: A finite number >= 0.
NonNegFinite = Annotated[float, Strict(), Field(ge=0, allow_inf_nan=False)]
#: A number > 0 that may be ``inf`` (no limit); NaN is refused.
PositiveOrInf = Annotated[float, Strict(), Field(gt=0, allow_inf_nan=True)]
#: A whole number >= 1 (an int; a bool or a float is not one).
WholePositive = Annotated[int, Strict(), Field(ge=1)]

_T = TypeVar("_T")


@functools.cache
def _positional_names(cls: type) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(cls) if f.init and not f.kw_only)


def _errors_by_field_name(cls: type, data: Any, handler: Callable[[Any], Any]) -> Any:
    """Validate; if that fails on positional arguments, again by name for the message.

    pydantic locates an error in a positional argument by its index (``0``), not by the field's
    name (pydantic issue 9140). Only a failed construction pays for the second pass.
    """
    try:
        return handler(data)
    except ValidationError:
        if type(data) is ArgsKwargs and data.args:
            names = _positional_names(cls)
            named = dict(zip(names, data.args, strict=False))
            kwargs = data.kwargs or {}
            if len(data.args) <= len(names) and named.keys().isdisjoint(kwargs):
                return handler(ArgsKwargs((), {**named, **kwargs}))
        raise


@dataclass_transform(field_specifiers=(dataclasses.field, Field))
def params_dataclass(
    *, frozen: bool = False, slots: bool = False, kw_only: bool = False
) -> Callable[[type[_T]], type[_T]]:
    """A pydantic dataclass with :data:`PARAMS_CONFIG`, for a parameter or configuration class.

    Used as ``@params_dataclass(frozen=True, slots=True)``: the class stays a dataclass
    (``dataclasses.replace``, ``fields``, ``asdict``, equality and hashing as before), its fields'
    annotations (:data:`PositiveFinite`, ...) are checked on construction, a ``__post_init__``
    then checks what involves several fields, and a validation error names the field also for an
    argument given by position.
    """

    def wrap(cls: type[_T]) -> type[_T]:
        cls._errors_by_field_name = model_validator(mode="wrap")(  # type: ignore[attr-defined]
            _errors_by_field_name
        )
        made = pydantic.dataclasses.dataclass(
            frozen=frozen, slots=slots, kw_only=kw_only, config=PARAMS_CONFIG
        )(cls)
        return cast("type[_T]", made)

    return wrap


_BOUNDS = {"gt": ">", "ge": ">=", "lt": "<", "le": "<="}
_KINDS = {
    "float_type": "a number",
    "int_type": "a whole number",
    "bool_type": "True or False",
    "string_type": "a string",
    "finite_number": "finite",
}


def describe(exc: ValidationError, units: Mapping[str, str] | None = None) -> str:
    """The first problem of a validation error on one line: ``FIELD must be BOUND, got VALUE``.

    For messages printed to a user of a command line or a file, where the multi-line
    :class:`pydantic.ValidationError` text is too much. ``units`` maps a field to its unit, added
    as ``[UNIT]`` after the bound.

    Examples
    --------
    >>> from haptic_collab.server.objects.balloon import BalloonParams
    >>> try:
    ...     BalloonParams(tension=-1.0)
    ... except ValidationError as exc:
    ...     print(describe(exc))
    tension must be > 0, got -1.0
    """
    err = exc.errors(include_url=False)[0]
    where = ".".join(str(p) for p in err["loc"])
    ctx = err.get("ctx") or {}
    bound = next((f"{op} {_number(ctx[k])}" for k, op in _BOUNDS.items() if k in ctx), None)
    what = bound or _KINDS.get(err["type"])
    if what is None:  # another kind of problem: pydantic's own words
        msg = err["msg"].removeprefix("Value error, ")
        return f"{where}: {msg}" if where else msg
    unit = (units or {}).get(where)
    return f"{where} must be {what}" + (f" [{unit}]" if unit else "") + f", got {err['input']!r}"


def _number(value: object) -> str:
    return f"{value:g}" if isinstance(value, int | float) else str(value)


def positive(name: str, value: float) -> float:
    """``value`` as a float if it is finite and > 0.

    Raises
    ------
    ValueError
        ``NAME must be a finite number > 0, got VALUE`` otherwise.
    """
    v = float(value)
    if not (math.isfinite(v) and v > 0.0):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return v


def nonneg(name: str, value: float) -> float:
    """``value`` as a float if it is finite and >= 0.

    Raises
    ------
    ValueError
        ``NAME must be a finite number >= 0, got VALUE`` otherwise.
    """
    v = float(value)
    if not (math.isfinite(v) and v >= 0.0):
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    return v


def whole(name: str, value: int, minimum: int = 0) -> int:
    """``value`` as an int if it is a whole number >= ``minimum`` (a bool is not a number).

    Raises
    ------
    ValueError
        ``NAME must be a whole number >= MINIMUM, got VALUE`` otherwise.
    """
    if isinstance(value, bool) or int(value) != value or value < minimum:
        raise ValueError(f"{name} must be a whole number >= {minimum}, got {value!r}")
    return int(value)
