import sys

try:
    from softphantom.cli import exit_with, main
except KeyboardInterrupt:  # Ctrl-C while starting: nothing done yet
    sys.exit(130)

exit_with(main())
