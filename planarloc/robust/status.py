"""The status of a pose estimate: ``success`` or the reason it failed.

``Status`` is a :class:`enum.StrEnum`: a member equals its string value (``Status.SUCCESS ==
"success"``), hashes like it and serialises to it in JSON, so results written as strings and
compared with strings read the same as before.
"""

from __future__ import annotations

from enum import StrEnum


class Status(StrEnum):
    """Why an absolute or relative pose estimate succeeded or failed."""

    SUCCESS = "success"
    #: too few matches (or 2D-3D constraints) for any minimal sample
    TOO_FEW_MATCHES = "too_few_matches"
    #: every hypothesis failed the checks
    NO_CONSISTENT_HYPOTHESIS = "no_consistent_hypothesis"
    #: the best pose has fewer than ``min_inliers`` inliers
    TOO_FEW_INLIERS = "too_few_inliers"
    #: the position along some axis is unobservable (or its std exceeds ``max_position_std_m``)
    DEGENERATE_SCALE = "degenerate_scale"
    #: the supporting map points lie on one plane seen from afar
    DEGENERATE_STRUCTURE = "degenerate_structure"
    #: all inliers come from one map image and no 2D-3D constraint fixes the scale
    SINGLE_REFERENCE = "single_reference"
    #: the map images disagree on the position
    INCONSISTENT_REFERENCES = "inconsistent_references"
    #: another pose far away explains the matches nearly as well
    AMBIGUOUS_POSE = "ambiguous_pose"
    #: the search stopped on its budget before it could rule out a pose of more support
    SEARCH_INCOMPLETE = "search_incomplete"
    #: an explicit planar method's model does not fit: a 6DoF pose far from it is clearly better
    PLANAR_MODEL_VIOLATED = "planar_model_violated"
    #: no retrieved map image sees the query (:mod:`planarloc.robust.covisibility`): the map does
    #: not hold the place (set by the localizer, which knows what retrieval tried)
    NOT_IN_MAP = "not_in_map"

    @classmethod
    def of(cls, value: str) -> Status | str:
        """The member whose value is ``value``; a string no member has is returned as given
        (a status made outside the estimators, e.g. by a test double)."""
        try:
            return cls(value)
        except ValueError:
            return value


#: failures of a pose that say the matches cannot single out a position, whatever the model
DATA_LIMITED = frozenset(
    {
        Status.DEGENERATE_SCALE,
        Status.DEGENERATE_STRUCTURE,
        Status.SINGLE_REFERENCE,
        Status.INCONSISTENT_REFERENCES,
        Status.AMBIGUOUS_POSE,
    }
)
