"""What one preprocessing did: the information layer's report beside the preprocessed set.

:func:`dtpf.information.rules.preprocess` returns it with the set; the information service sends its fields
in the preprocessed set's message (``threshold``, ``n_large``, ``n_processed``, ``n_mixed``, ``n_plain``,
``ps``), and the mirror and the system layer read W from it. The entity's filter keeps whatever report its
preprocessor gives without reading it (:class:`dtpf.entity.filter.Preprocessed`).
"""
from __future__ import annotations

from dataclasses import dataclass

__all__ = ["PreprocessReport"]


@dataclass(frozen=True)
class PreprocessReport:
    """What one preprocessing did.

    Attributes
    ----------
    threshold : float
        W of Eq. 28.
    n_large : int
        M, particles with weight > W (kept unchanged).
    n_processed : int
        N - M, particles moved by Eq. 29-30.
    n_mixed : int
        Processed particles that took the first branch of Eq. 30 (u <= PS).
    n_plain : int
        Processed particles that took the second branch (u > PS).
    ps : float
        The degree factor used.
    """

    threshold: float
    n_large: int
    n_processed: int
    n_mixed: int
    n_plain: int
    ps: float
