"""Entity layer: the running particle filter (paper section 3, Fig. 3).

Modules: :mod:`dtpf.entity.base` (the contract of a state-space model),
:mod:`dtpf.entity.models` (the built-in models and their registry),
:mod:`dtpf.entity.tracking` and :mod:`dtpf.entity.video` (the section-5 video model),
:mod:`dtpf.entity.resampling` (the four traditional schemes), :mod:`dtpf.entity.filter`
(the filter as an iterator, one step per ``next()``), :mod:`dtpf.entity.model_ref`,
:mod:`dtpf.entity.model_check`, :mod:`dtpf.entity.observations`, :mod:`dtpf.entity.sources`
and :mod:`dtpf.entity.intake` (the user's own model and observations),
:mod:`dtpf.entity.service` (its Zenoh shell). It may import only the wire contract
(:mod:`messages`): what it receives from the information layer is a message.
"""
