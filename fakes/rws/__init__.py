"""A fake ABB controller speaking Robot Web Services 1.0 and 2.0, written from ABB's
documents: routes and resources, logins, the peer."""
