import sys

try:
    from .cli import main
except KeyboardInterrupt:  # Ctrl-C while the command line loads: nothing has started
    sys.stderr.write("aborted\n")
    sys.exit(1)

main()
