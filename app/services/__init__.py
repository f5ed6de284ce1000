"""Use cases of the service: queries and changes, one commit per use case.

Routes stay thin: they parse the request, call one function here, and shape the
answer. Every function takes the database session and the acting
:class:`app.actors.Actor`, writes its audit event(s) in the same transaction,
and commits once. A lookup that fails is audited (``not_found``) and raised as
:class:`app.errors.NotFoundError`.
"""
