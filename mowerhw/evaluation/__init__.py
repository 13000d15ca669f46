"""Scoring the estimators against the simulator's truth: teach (:mod:`.teach`), mow
(:mod:`.mow`), pixel level (:mod:`.pixel`), the scenario × seed campaign (:mod:`.campaign`)."""
