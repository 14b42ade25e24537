"""The node types of the material graph, one module per family; importing the package registers them all.

Adding a node type is one module here (a :class:`NodeType` subclass with ``@register_node``) plus its test: every
module of this package is imported (in name order) when the package is.
"""
import importlib
import pkgutil

from .base import NODE_TYPES, EvalContext, NodeType, Param, Slot, as3, gaussian_blur, numbers, register_node

for _module in pkgutil.iter_modules(__path__):
    importlib.import_module(f"{__name__}.{_module.name}")

__all__ = ["NODE_TYPES", "EvalContext", "NodeType", "Param", "Slot", "as3", "gaussian_blur", "numbers", "register_node"]
