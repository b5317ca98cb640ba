"""Which topics of a recording `gcp-stereo-bag run` reads: the stereo pair, camera_info."""
from .files import IMAGE_TYPES, INFO


def _stereo_namespace(left, right):
    """
    Return the part of two image topics before their left/right token; None if not a pair.

    E.g. /cam/left/image_rect + /cam/right/image_rect -> '/cam', /left/image + /right/image
    -> '': the topics differ in one token only, which holds 'left' in one, 'right' in the other.
    """
    a, b = left.strip('/').split('/'), right.strip('/').split('/')
    differ = [i for i, (x, y) in enumerate(zip(a, b)) if x != y]
    if len(a) != len(b) or len(differ) != 1:
        return None
    i = differ[0]
    if 'left' not in a[i] or a[i].replace('left', 'right') != b[i]:
        return None
    return '/' + '/'.join(a[:i]) if i else ''


def _info_topic(image_topic):
    """Return the camera_info topic beside an image topic, as image_transport finds it."""
    base = image_topic.removesuffix('/compressed')
    return base.rsplit('/', 1)[0] + '/camera_info'


def find_topics(reader, path, args):
    """
    Return the topics `run` reads, by role, and the output namespace.

    {'left', 'right': image topic, 'left_info', 'right_info': camera_info topic or None,
    'ns': namespace of the outputs and ground truth}.

    Raises ValueError naming the bag's topics when the stereo pair cannot be found, or when a
    topic is missing or of the wrong type.
    """
    types = {c.topic: c.msgtype for c in reader.connections}
    listing = ', '.join(f'{t} ({m.rsplit("/", 1)[1]})' for t, m in sorted(types.items())) or 'none'
    ns = args.namespace.strip('/')
    if args.left or args.right:
        if not (args.left and args.right):
            raise ValueError('--left and --right go together')
        left, right = args.left, args.right
    else:
        images = [t for t, m in types.items() if m in IMAGE_TYPES
                  and (not ns or t.startswith(f'/{ns}/'))]
        pairs = [(t, u) for t in images for u in images if _stereo_namespace(t, u) is not None]
        if len(pairs) != 1:
            found = ('; stereo pairs: ' + ', '.join(f'{a} + {b}' for a, b in pairs)
                     if pairs else '')
            raise ValueError(f'{path}: {"no" if not pairs else "more than one"} stereo pair of '
                             f'image topics (topics: {listing}){found}; name them with --left '
                             'and --right')
        (left, right), = pairs
    topics = {'left': left, 'right': right,
              'left_info': args.left_info or _info_topic(left),
              'right_info': args.right_info or _info_topic(right)}
    for role, topic in topics.items():
        want = (INFO,) if role.endswith('info') else IMAGE_TYPES
        if topic not in types:
            if role.endswith('info') and not getattr(args, role):
                topics[role] = None  # no calibration: no depth or points2
                continue
            raise ValueError(f'{path}: no {topic} topic (topics: {listing})')
        if types[topic] not in want:
            raise ValueError(f'{path}: {topic} is {types[topic]}, expected {" or ".join(want)}')
    topics['ns'] = f'/{ns}' if ns else _stereo_namespace(left, right) or ''
    return topics
