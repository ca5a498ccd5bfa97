"""Entity layer: the running particle filter (paper section 3, Fig. 3).

Modules: :mod:`entity.base` (the contract of a state-space model),
:mod:`entity.models` (the built-in models and their registry),
:mod:`entity.tracking` and :mod:`entity.video` (the section-5 video model),
:mod:`entity.resampling` (the four traditional schemes), :mod:`entity.filter`
(the filter as an iterator, one step per ``next()``), :mod:`entity.model_ref`,
:mod:`entity.model_check`, :mod:`entity.observations`, :mod:`entity.sources`
and :mod:`entity.intake` (the user's own model and observations),
:mod:`entity.service` (its Zenoh shell). It may import only the wire contract
(:mod:`messages`): what it receives from the information layer is a message.
"""
