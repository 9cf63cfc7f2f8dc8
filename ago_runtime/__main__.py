from ago_runtime.cli import main

main()
