"""Kernel signatures as ``kernels.json`` writes them (``repr`` of a tuple of numba types), read
back as data: never evaluated as code beyond numba type names, calls and subscripts of them, constants
and tuples (``Literal[int](5)``: the type of a constant argument)."""

from __future__ import annotations

import ast
import re
from collections.abc import Callable


class _LiteralOf:
    """``Literal[int](5)``, ``Literal[bool](True)`` (the repr of numba's literal types) -> the type of
    that constant: a kernel called with a constant argument compiles a specialisation for its value."""

    def __getitem__(self, _kind: object) -> Callable[[object], object]:
        from numba.core import types

        return types.literal


def numba_types() -> dict[str, object]:
    """The names a signature may use: numba's type names, plus ``bool``, ``omitted`` and the
    literal types (``Literal[int](5)``)."""
    from numba.core import types

    names = {k: v for k, v in vars(types).items() if not k.startswith("_")}
    names["bool"] = types.boolean  # repr(types.boolean) is 'bool'
    names["omitted"] = lambda default: types.Omitted(default)  # repr: 'omitted(default=...)'
    names["Literal"] = _LiteralOf()
    names["int"] = int  # only as the subscript of ``Literal[int]``
    # the kernels' named records (typing.NamedTuple): repr 'ProblemArrays(array(float64, 2d, C), ...)'
    for record in kernel_records():
        names[record.__name__] = _record_type(record)
    return names


def kernel_records() -> tuple[type, ...]:
    """The named records (``typing.NamedTuple`` of arrays and numbers) the kernels take as arguments."""
    from planarloc.robust.consensus_scale import (
        ConsensusSettings,
        PairMotions,
        RelativeCandidates,
        ScaleVotes,
    )
    from planarloc.robust.hypotheses import Hypotheses, RelativePoses
    from planarloc.robust.local_optimization import LocalOptimization
    from planarloc.robust.problem import ProblemArrays
    from planarloc.robust.refinement import RefineSettings, StartPose
    from planarloc.robust.relative_pose import RayPairs

    return (
        ProblemArrays,
        RelativePoses,
        Hypotheses,
        PairMotions,
        ScaleVotes,
        StartPose,
        RefineSettings,
        LocalOptimization,
        ConsensusSettings,
        RelativeCandidates,
        RayPairs,
    )


def _record_type(record: type) -> Callable[..., object]:
    """``Record(field types...)`` -> numba's type of that record."""
    from numba.core import types

    return lambda *fields: types.NamedTuple(fields, record)


#: An array as a record's repr writes its fields (``str`` of the type): ``array(float64, 2d, C)``.
_SHORT_ARRAY = re.compile(r"\barray\((\w+), (\d)d, ([CFA])\)")


#: The expressions a signature may use: type names, calls and subscripts of them
#: (``array(float64, 1d, C)``, ``Literal[int](0)``), constants and tuples; no operators or attributes.
_SIGNATURE_NODES = (
    ast.Expression,
    ast.Tuple,
    ast.Name,
    ast.Call,
    ast.keyword,
    ast.Subscript,
    ast.Constant,
    ast.Load,
    ast.UnaryOp,
    ast.USub,
)


def parse_signature(text: str, names: dict[str, object] | None = None) -> tuple | None:
    """The argument types of a signature written as ``repr(tuple_of_numba_types)``; None if it
    does not parse or is not made only of numba type names, calls, subscripts, constants and
    tuples (the list is data: it is never evaluated as code beyond that)."""
    try:
        text = _SHORT_ARRAY.sub(r"Array(\1, \2, '\3')", text)
        if (
            not isinstance(text, str)
            or len(text) > 4000
            or not all(isinstance(n, _SIGNATURE_NODES) for n in ast.walk(ast.parse(text, mode="eval")))
        ):
            return None
        sig = eval(text, {"__builtins__": {}}, names or numba_types())  # noqa: S307 - numba type names only
    except Exception:  # noqa: BLE001 - any failure: the kernel is compiled by the steps instead
        return None
    return sig if isinstance(sig, tuple) else None
