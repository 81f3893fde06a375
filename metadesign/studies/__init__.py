"""Studies: what combines stages, on top of them (prysm's ``x``).  Nothing below imports from here.

* :mod:`.demo` (``metadesign demo``) and :mod:`.pipeline` (``metadesign run``): every stage, end to end.
* :mod:`.compare` (``compare``, ``retrieve``): every wavefront estimator on the same samples.
* :mod:`.tolerance` (``tolerance``): reconstruction-level fab tolerance.
* :mod:`.transfer` (``transfer``) and :mod:`.captures` (``dataset synth-captures``): fab to lab.
* :mod:`.table_s2` (``table-s2``): the paper's loss selection.
* :mod:`.lpa` (``library lpa-check``): the local-periodic approximation's error on a design, downstream.
"""
