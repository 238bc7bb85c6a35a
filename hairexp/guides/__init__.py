"""Guide hair: the animation a run tracks (``animation``), the artist's edits and keyframes
(``authoring``), the parallel-transported frames carried by the body (``frames``, paper 3.2) and
arc-length Catmull-Rom splines (``spline``, paper 3.2)."""
