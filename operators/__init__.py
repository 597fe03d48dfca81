# Placeholder until the UI layer lands: keeps the root register() working.


def register():
    pass


def unregister():
    pass
