"""The device boundary: abstract interfaces (:mod:`drivers.interfaces`) and their implementations.

Concrete drivers depend on the core's data types only; the core depends on the interfaces only.
"""
