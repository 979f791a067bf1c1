"""``flexure-ctrl recover BAG``: make a bag whose recorder was killed complete again."""

import argparse
from pathlib import Path

from flexure_ctrl.core.bag import BagReader, recover


def add_parser(commands) -> None:
    parser = commands.add_parser(
        'recover', help='rewrite a bag whose recorder was killed as a complete bag',
        description='A recorder killed by SIGKILL or a crash leaves an MCAP file without its '
                    'summary (the messages up to its last flush are in it). This rewrites '
                    'the bag with every readable message, its summary and metadata.yaml, in '
                    'place or into --out.')
    parser.add_argument('bag', type=Path, metavar='BAG', help='the bag folder')
    parser.add_argument('--out', type=Path, default=None, metavar='DIR',
                        help='write the complete bag here (default: replace it in place)')
    parser.set_defaults(run=run)


def run(arguments: argparse.Namespace) -> int:
    if BagReader(arguments.bag).complete:
        print(f'{arguments.bag} is complete already; nothing to do')
        return 0
    folder = recover(arguments.bag, arguments.out)
    print(f'recovered {BagReader(folder).message_count} messages into {folder}')
    return 0
