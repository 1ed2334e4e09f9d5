"""report: what a fit says: the uncertainty report, the misfit check, the result table
and files.

The floor's public face, listed in `__all__`; the rest stays in its modules. fitting's
own modules import each other by full module path.
"""

from fitting.report.misfit import Misfit
from fitting.report.result import comparison_table, mtl_text
from fitting.report.uncertainty import IdentifiabilityWarning, UncertaintyReport

__all__ = [
    "Misfit", "comparison_table", "mtl_text", "IdentifiabilityWarning", "UncertaintyReport",
]
