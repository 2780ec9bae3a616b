"""File input for the core: point lists (and later plans) from the files planning software writes,
and recorded respiratory motion traces (docs/traces.md)."""

from hil.io.points import PointSet, read_points
from hil.io.traces import Trace, TraceError, TraceFormat, read_trace, resample, trace_summary

__all__ = ["PointSet", "Trace", "TraceError", "TraceFormat", "read_points", "read_trace", "resample",
           "trace_summary"]
