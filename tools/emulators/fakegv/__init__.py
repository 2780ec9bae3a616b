"""Fake GigE Vision cameras serving custom images (Aravis GvFakeCamera + a ctypes fill callback)."""
