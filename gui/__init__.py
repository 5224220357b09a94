"""The PySide6 + pyqtgraph desktop application: the only place Qt is imported."""
