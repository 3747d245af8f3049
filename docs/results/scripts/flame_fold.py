"""Folded perf stacks (`inferno-collapse-perf`) made readable for a flame graph of a run.

Generic arguments and closure environments are stripped from each frame, and only the frames
that name capsule-slam's or faer's code (and the leaf) are kept, so that rayon's plumbing
between them does not hide the application's structure; equal stacks are merged.

    perf record -F 300 --call-graph dwarf,32768 -o perf.data capsule-slam run --input SEQ ...
    perf script -i perf.data | inferno-collapse-perf | python3 flame_fold.py | inferno-flamegraph > flame.svg
"""
import collections
import re
import sys


def strip_generics(frame):
    out, depth = [], 0
    for ch in frame:
        if ch == '<':
            depth += 1
        elif ch == '>' and depth:
            depth -= 1
        elif depth == 0:
            out.append(ch)
    return re.sub(r'\{closure_env#\d+\}|::\{\{closure\}\}|\{closure#\d+\}', '{closure}', ''.join(out))


def main():
    merged = collections.Counter()
    for line in sys.stdin:
        stack, count = line.rstrip('\n').rsplit(' ', 1)
        frames = [strip_generics(f) for f in stack.split(';')]
        keep = [f for f in frames[:-1] if 'capsule_slam' in f or 'faer' in f]
        if not keep or keep[-1] != frames[-1]:
            keep.append(frames[-1])
        merged[';'.join(['capsule-slam'] + keep)] += int(count)
    for stack, count in merged.items():
        print(stack, count)


if __name__ == '__main__':
    main()
