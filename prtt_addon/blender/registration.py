"""register()/unregister() of every Blender class and property PRTT adds."""


from . import commands
from .preview import draw as preview_draw
from .ui import operators, panels, properties

_MODULES = (properties, operators, panels, preview_draw)


def register():
    for m in _MODULES:
        m.register()
    commands.register()


def unregister():
    commands.unregister()
    for m in reversed(_MODULES):
        m.unregister()



