"""What the forward model reports along one protocol: the channels at every output point
and, when asked, their sensitivities to the model's parameters (keyed by ``Param``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from .parameters import Param
from .vocabulary import CONTROL, OUTPUT_COLUMNS, TIME


@dataclass
class Response:
    """Output points of one protocol.

    ``values[column]``: the reported column at every output point (``OUTPUT_COLUMNS`` of the
    test); ``jacobian[param][column]``: its partial derivative with respect to ``param``.
    With plates that cannot pull, ``in_contact`` (bool per point) and ``contact_events``
    (:class:`~brain_fe.contact.ContactEvent`: lift-off, re-contact).
    """

    test: str
    time_s: np.ndarray
    cycle: np.ndarray
    branch: np.ndarray
    control: np.ndarray
    values: dict[str, np.ndarray]
    jacobian: dict[Param, dict[str, np.ndarray]] = field(default_factory=dict)
    in_contact: np.ndarray | None = None
    contact_events: list = field(default_factory=list)

    @classmethod
    def from_rows(cls, test: str, rows: list[dict], sens: list[dict]) -> Response:
        """``rows``: one dict per point (time_s, cycle, branch, control, columns...);
        ``sens``: per point ``{param: {column: derivative}}``."""
        cols = OUTPUT_COLUMNS[test]

        def arr(key, dtype=float):
            return np.array([r[key] for r in rows], dtype=dtype)

        params = list(dict.fromkeys(p for s in sens for p in s))
        jac = {p: {c: np.array([s[p][c] for s in sens]) for c in cols} for p in params}
        contact = arr("in_contact", bool) if rows and "in_contact" in rows[0] else None
        return cls(test, arr(TIME), arr("cycle", int), arr("branch", object),
                   arr("control"), {c: arr(c) for c in cols}, jac, contact)

    def __len__(self) -> int:
        return len(self.time_s)

    def derivative(self, column: str, param: Param) -> np.ndarray:
        return self.jacobian[param][column]

    def add_offsets(self, offsets: dict[str, float]) -> None:
        for c, v in offsets.items():
            self.values[c] = self.values[c] + v

    def frame(self) -> pd.DataFrame:
        """The table view: ``time_s, cycle, branch, stretch|shear``, the reported columns,
        then ``d_<column>/d_<param>`` for every sensitivity."""
        df = pd.DataFrame({TIME: self.time_s, "cycle": self.cycle, "branch": self.branch,
                           CONTROL[self.test]: self.control})
        for c, v in self.values.items():
            df[c] = v
        if self.in_contact is not None:
            df["in_contact"] = self.in_contact.astype(int)
        for p, cols in self.jacobian.items():
            for c, v in cols.items():
                df[f"d_{c}/d_{p}"] = v
        return df
