"""register()/unregister() of every Blender class and property PRTT adds."""


from . import cli
from .ui import operators, panels, properties
from .preview import draw as preview_draw

_MODULES = (properties, operators, panels, preview_draw)


def register():
    for m in _MODULES:
        m.register()
    cli.register()


def unregister():
    cli.unregister()
    for m in reversed(_MODULES):
        m.unregister()



