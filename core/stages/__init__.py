"""Every stage of the pipeline, declared once (see :mod:`core.stage` for what a stage is).

Importing this package registers them: the retargeting stages (:mod:`.retarget`), whose solve
stage dispatches to the registered methods (:mod:`.methods`), the dense-transfer stages of
Xu 2014 (:mod:`.dense`), a mesh-sequence source's own face (:mod:`.sequence`) and the normal-map stages of Liu 2011 §5 (:mod:`.normalmap`)
and what a page shows of a retargeting result (:mod:`.snapshot`).
"""

# isort: skip_file  (the order is the registration order: stages and methods are listed in it)
from .methods import METHODS, Method, method_of, solve_method  # noqa: F401
from . import retarget  # noqa: F401  (registers)
from . import dense  # noqa: F401
from . import sequence  # noqa: F401  (a mesh sequence's own source face)
from . import normalmap  # noqa: F401
from . import snapshot  # noqa: F401  (what a page shows of a result)
from .retarget import INVISIBLE, solver_shapes  # noqa: F401

#: methods that use the PCA prior stage (derived from the registrations)
PRIOR_METHODS = tuple(n for n, m in METHODS.items() if "prior" in m.needs)
