"""Entity layer: the running particle filter (paper section 3, Fig. 3).

Modules: :mod:`entity.models` (state-space models), :mod:`entity.resampling`
(the four traditional schemes), :mod:`entity.filter` (the filter as an
iterator, one step per ``next()``).
"""
