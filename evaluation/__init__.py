"""The evaluation: the thesis' experiments on recordings with a reference, scored against the
truth the estimator never sees. Every fusion run goes through the server's own engine path
(``engine.driver``, ``engine.targets``). ``berthing-aid replay --report`` is ``report``; the
compass and two-receiver baseline reports are ``compass`` and ``baseline``."""
