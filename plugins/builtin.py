"""The built-in drivers, registered through the same hooks as third-party plugins."""
