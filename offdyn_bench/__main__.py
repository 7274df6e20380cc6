from offdyn_bench.cli import main

main()
