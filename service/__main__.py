"""``python -m shadowcorr_service [flags]``: run the HTTP service (see ``shadowcorr_service.cli``)."""

# Guarded: spawned worker processes import the main module as "__mp_main__", and must not
# start a second server.
if __name__ == "__main__":
    import sys

    from shadowcorr_service.cli import main

    sys.exit(main())
