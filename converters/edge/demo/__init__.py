"""The demo: a synthetic room (:mod:`.scene`), the run that records it (:mod:`.run`), its PNG
views (:mod:`.views`, drawing with :mod:`.viz`)."""
