"""Judging runs: each paper scene's success measure (``measures``, ``stylization``) and the
judges that compare an experiment's variants (``judges``)."""
