"""The shell of a layer's process: what every service does on the bus.

Modules: :mod:`dtpf.shell.bus` (Zenoh configuration, sessions, the inbox and
presence), :mod:`dtpf.shell.service` (one service's loop: admission, counts,
statuses, exit), :mod:`dtpf.shell.fleet` (one service serving many twins) and
:mod:`dtpf.shell.secure` (mutual TLS and access control files). The layers'
services (``dtpf.entity.service`` and its siblings) are thin wrappers around
it. It may import the wire contract (:mod:`dtpf.messages`) and nothing above.
"""
