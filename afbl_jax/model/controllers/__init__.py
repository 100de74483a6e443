"""Controllers: one interface (`AbstractController`), pure functions, states in the ODE."""

from ._any import LAWS as LAWS
from ._any import AnyController as AnyController
from ._base import AbstractController as AbstractController
from ._base import ReferenceSample as ReferenceSample
from .afbl import AFBL as AFBL
from .afbl import DEFAULT_LAMBDA as DEFAULT_LAMBDA
from .afbl import PAPER_AFBL_GAINS as PAPER_AFBL_GAINS
from .afbl import AFBLPaper as AFBLPaper
from .fbl_pid import FBLPID as FBLPID
from .fbl_pid import PAPER_FBL_GAINS as PAPER_FBL_GAINS

CONTROLLERS: dict[str, type[AbstractController]] = {
    FBLPID.name: FBLPID,
    AFBL.name: AFBL,
    AFBLPaper.name: AFBLPaper,
}
"""Controller classes by name: "fbl", "afbl", "afbl_paper"."""


def make_controller(name: str, **gains) -> AbstractController:
    """Controller by name with the paper's gains, overridden by ``gains`` (arrays of 4)."""
    try:
        cls = CONTROLLERS[name]
    except KeyError:
        raise ValueError(
            f"unknown controller {name!r}; allowed: {', '.join(CONTROLLERS)}."
        ) from None
    unknown = set(gains) - set(cls.gain_names)
    if unknown:
        raise ValueError(
            f"controller {name!r} has gains {', '.join(cls.gain_names)}; got unknown "
            f"{', '.join(sorted(unknown))}."
        )
    return cls(**gains)
