#!/usr/bin/env python3
"""ROS 2 .msg files -> one IDL file with the DDS types rmw_cyclonedds_cpp puts on the wire.

usage: msg2idl.py [--out FILE] PKG/msg/Name.msg...

Each input's package is the name of the folder above its msg/ folder (ros2/std_msgs/msg/
Header.msg is std_msgs/Header). The output holds every input message, dependencies first, each
once, as

    module <pkg> { module msg { module dds_ { struct <Name>_ { ... }; }; }; };

It shares nothing with pulsetrack's own IDL (msgs/idl): it is how a ROS 2 node built from the
.msg files registers the types, so tests/ros2_compat can show the daemon's topics match one.

What this follows, read in the sources (ROS 2 Humble branches: rosidl 41be8d6e (3.1.6),
rmw_cyclonedds 7cb3b38a (1.3.4); Cyclone DDS tag 0.10.2, the version Debian 12 ships; Humble's
rmw_cyclonedds builds on Cyclone 0.10.x, and its Jazzy and Rolling branches still register types
keyless, XCDR1-only and without type information):

* github:ros2/rosidl rosidl_adapter/rosidl_adapter/parser.py (parse_message_string, Type,
  BaseType): tabs become spaces; everything from the first '#' on a line is a comment (also
  inside a string default, as there); a line is "<type> <name>[ <default>]" or, when the part
  after the type contains '=', a constant "<type> <NAME>=<value>"; "<type>[]" is unbounded,
  "<type>[<=N]" bounded, "<type>[N]" fixed; "string<=N" / "wstring<=N" are bounded strings;
  "pkg/Type" names a message of another package, a bare "Type" one of the same package. Name
  patterns (package, field, message, constant) are checked with the same regular expressions.
  "time" and "duration" are accepted by its parser but have no IDL mapping (KeyError in
  get_idl_type), so they are refused here. wstring (-> wstring in rosidl) is refused too: idlc 0.10
  has no wstring, and rmw_cyclonedds (Serialization.cpp) writes it as wchar_t units.
* rosidl_adapter/rosidl_adapter/msg/__init__.py (MSG_TYPE_TO_IDL, get_idl_type): bool->boolean,
  byte->octet, char->uint8, int8..uint64 unchanged, float32->float, float64->double,
  string->string (string<N> if bounded); T[]->sequence<T>,
  T[<=N]->sequence<T, N>, T[N]->an array (rosidl writes a typedef T T__N[N]; the member
  "T name[N]" written here is the same type and wire format). resource/struct.idl.em: constants
  go to a separate module <Name>_Constants (never on the wire: skipped here), defaults become
  @default annotations (never on the wire: ignored here), comments become @verbatim (dropped),
  and a message without fields gets "uint8 structure_needs_at_least_one_member" (done here too).
  No member is ever @key.
* github:ros2/rmw_cyclonedds rmw_cyclonedds_cpp/src/serdata.cpp (create_type_name,
  create_sertype) and MessageTypeSupport_impl.hpp: the DDS type name is the message namespace
  with "__" turned into "::" ("pulsetrack_msgs::msg"), then "::dds_::", the message name and a
  trailing "_": "pulsetrack_msgs::msg::dds_::Features_". The sertype is created with
  DDSI_SERTYPE_FLAG_TOPICKIND_NO_KEY (keyless: "ROS 2 doesn't support keys") and
  allowed_data_representation = DDS_DATA_REPRESENTATION_FLAG_XCDR1 (plain CDR, XCDR1 only);
  sertype_rmw_ops leaves the type-information hooks NULL ("not yet providing type discovery,
  assignability checking"), so a ROS 2 Humble endpoint sends no TypeInformation and Cyclone
  matches it by type name alone (q_qosmatch.c, qos_match_mask_p: "If either the reader or
  writer does not provide a type id, the type names are consulted"). Nested types never appear
  on the wire, only the top-level type's name and the CDR of its members in order; they are
  named the same way here (std_msgs::msg::dds_::Header_, ...) for consistency.
  rmw_node.cpp: topics are "rt" + the fully qualified ROS name ("rt/pulsetrack/features"); the
  reader/writer QoS comes from the rmw profile (create_readwrite_qos).
* github:eclipse-cyclonedds/cyclonedds 0.10.2 src/core/ddsi/src/ddsi_entity_match.c
  (topickind_qos_match_p_lock): a keyed endpoint never matches a keyless one (the entity id kind
  is compared, silently: no incompatible-QoS status), so the generated types must stay keyless
  like ROS 2's, and so must the daemon's.

Names that are IDL keywords (case-insensitively, as IDL compares them) are escaped the IDL way,
with a leading '_' (the identifier itself is unchanged); field names that are C keywords get a
trailing '_' in the IDL (idlc's C output would not compile otherwise). Field names are not on
the wire (types are matched by name and decoded by position), so neither changes the format.
"""

import argparse
import os
import re
import sys

# rosidl_adapter/parser.py
PRIMITIVE_TYPES = [
    'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16', 'int32',
    'uint32', 'int64', 'uint64', 'string', 'wstring', 'duration', 'time'
]
VALID_PACKAGE_NAME_PATTERN = re.compile('^(?!.*__)(?!.*_$)[a-z][a-z0-9_]*$')
VALID_FIELD_NAME_PATTERN = VALID_PACKAGE_NAME_PATTERN
VALID_MESSAGE_NAME_PATTERN = re.compile('^[A-Z][A-Za-z0-9]*$')
VALID_CONSTANT_NAME_PATTERN = re.compile('^[A-Z]([A-Z0-9_]?[A-Z0-9]+)*$')

# rosidl_adapter/msg/__init__.py
MSG_TYPE_TO_IDL = {
    'bool': 'boolean',
    'byte': 'octet',
    'char': 'uint8',
    'int8': 'int8',
    'uint8': 'uint8',
    'int16': 'int16',
    'uint16': 'uint16',
    'int32': 'int32',
    'uint32': 'uint32',
    'int64': 'int64',
    'uint64': 'uint64',
    'float32': 'float',
    'float64': 'double',
    'string': 'string',
    'wstring': 'wstring',
}

# IDL 4.2 keywords (section 7.2.4) and the integer types idlc knows; IDL compares them
# case-insensitively.
IDL_KEYWORDS = {
    k.lower()
    for k in '''abstract any alias attribute bitfield bitmask bitset boolean case char component
    connector const consumes context custom default double exception emits enum eventtype factory
    FALSE finder fixed float getraises getter home import in inout interface local long manages map
    mirrorport module multiple native Object octet oneway out primarykey private port porttype
    provides public publishes raises readonly setraises setter sequence short string struct
    supports switch TRUE truncatable typedef typeid typename typeprefix unsigned union uses
    ValueBase valuetype void wchar wstring int8 uint8 int16 uint16 int32 uint32 int64
    uint64'''.split()
}
C_KEYWORDS = set('''auto break case char const continue default do double else enum extern float for
goto if inline int long register restrict return short signed sizeof static struct switch
typedef union unsigned void volatile while bool true false alignas alignof asm noreturn
static_assert thread_local'''.split())


class MsgError(Exception):
    pass


class FieldType:
    """A field's type: base (primitive name or (pkg, Name)), string bound, array kind/size."""

    def __init__(self, text, pkg, where):
        self.array = None  # None, 'fixed', 'bounded', 'unbounded'
        self.size = None
        base = text
        if text.endswith(']'):
            i = text.rfind('[')
            if i < 0:
                raise MsgError(f"{where}: the type '{text}' ends with ']' but has no '['")
            inner = text[i + 1:-1]
            base = text[:i]
            if inner == '':
                self.array = 'unbounded'
            else:
                bounded = inner.startswith('<=')
                digits = inner[2:] if bounded else inner
                if not digits.isdigit() or int(digits) <= 0:
                    raise MsgError(f"{where}: the size of the array type '{text}' must be an "
                                   "integer > 0, optionally prefixed with '<='")
                self.array = 'bounded' if bounded else 'fixed'
                self.size = int(digits)
        self.string_bound = None
        self.msg = None  # (pkg, Name) for a nested message
        if base == 'wstring' or base.startswith('wstring<='):
            raise MsgError(f"{where}: wstring is not supported: Cyclone 0.10's idlc has no "
                           "wstring, and rmw_cyclonedds writes it as wchar_t units, whose size "
                           "is the platform's")
        if base in PRIMITIVE_TYPES:
            if base in ('time', 'duration'):
                raise MsgError(f"{where}: '{base}' is not a ROS 2 type (use "
                               f"builtin_interfaces/{base.capitalize()})")
            self.primitive = base
        elif base.startswith('string<='):
            self.primitive, _, bound = base.partition('<=')
            if not bound.isdigit() or int(bound) <= 0:
                raise MsgError(f"{where}: the upper bound of the string type '{base}' must be an "
                               "integer > 0")
            self.string_bound = int(bound)
        else:
            self.primitive = None
            parts = base.split('/')
            if len(parts) == 2:
                ref_pkg, name = parts
            elif len(parts) == 1:
                ref_pkg, name = pkg, parts[0]
            else:
                raise MsgError(f"{where}: '{base}' is not a type")
            if not VALID_PACKAGE_NAME_PATTERN.match(ref_pkg):
                raise MsgError(f"{where}: '{ref_pkg}' is not a valid package name")
            if not VALID_MESSAGE_NAME_PATTERN.match(name):
                raise MsgError(f"{where}: '{name}' is not a valid message name (nor a primitive "
                               "type)")
            self.msg = (ref_pkg, name)

    def idl_element(self):
        if self.msg is not None:
            return '::' + '::'.join(
                (idl_identifier(self.msg[0]), 'msg', 'dds_', self.msg[1] + '_'))
        t = MSG_TYPE_TO_IDL[self.primitive]
        if self.string_bound is not None:
            t += f'<{self.string_bound}>'
        return t


class Field:

    def __init__(self, ftype, name, line):
        self.type = ftype
        self.name = name
        self.line = line


class Message:

    def __init__(self, pkg, name, path):
        self.pkg = pkg
        self.name = name
        self.path = path
        self.fields = []

    @property
    def key(self):
        return (self.pkg, self.name)


def idl_identifier(name):
    return '_' + name if name.lower() in IDL_KEYWORDS else name


def idl_member_name(name):
    if name in C_KEYWORDS:
        name += '_'
    return idl_identifier(name)


def package_of(path):
    """<...>/<pkg>/msg/<Name>.msg -> (pkg, Name)."""
    ap = os.path.abspath(path)
    msg_dir = os.path.dirname(ap)
    if os.path.basename(msg_dir) != 'msg' or not ap.endswith('.msg'):
        raise MsgError(f'{path}: expected <package>/msg/<Name>.msg')
    pkg = os.path.basename(os.path.dirname(msg_dir))
    name = os.path.basename(ap)[:-len('.msg')]
    if not VALID_PACKAGE_NAME_PATTERN.match(pkg):
        raise MsgError(f"{path}: '{pkg}' is not a valid ROS 2 package name")
    if not VALID_MESSAGE_NAME_PATTERN.match(name):
        raise MsgError(f"{path}: '{name}' is not a valid ROS 2 message name")
    return pkg, name


def parse_msg(path):
    pkg, name = package_of(path)
    msg = Message(pkg, name, path)
    with open(path, encoding='utf-8') as f:
        text = f.read().replace('\t', ' ')
    seen = set()
    for lineno, raw in enumerate(text.splitlines(), 1):
        where = f'{path}:{lineno}'
        line = raw
        hash_at = line.find('#')
        if hash_at >= 0:
            line = line[:hash_at]
        line = line.strip()
        if not line:
            continue
        type_text, _, rest = line.partition(' ')
        rest = rest.lstrip()
        if not rest:
            raise MsgError(f"{where}: '{line}' is neither a field nor a constant")
        if '=' in rest:  # a constant: not part of the data on the wire
            cname = rest.partition('=')[0].rstrip()
            if not VALID_CONSTANT_NAME_PATTERN.match(cname):
                raise MsgError(f"{where}: '{cname}' is not a valid constant name")
            if type_text not in PRIMITIVE_TYPES:
                raise MsgError(f"{where}: the constant type '{type_text}' must be primitive")
            continue
        fname = rest.partition(' ')[0]  # what follows is a default value: not on the wire
        if not VALID_FIELD_NAME_PATTERN.match(fname):
            raise MsgError(f"{where}: '{fname}' is not a valid field name")
        if fname in seen:
            raise MsgError(f"{where}: the field '{fname}' is defined twice")
        seen.add(fname)
        msg.fields.append(Field(FieldType(type_text, pkg, where), fname, lineno))
    return msg


def topological(messages):
    """Every message after the messages it uses; ties in (package, name) order."""
    order, state = [], {}

    def visit(key, chain):
        if state.get(key) == 'done':
            return
        if state.get(key) == 'active':
            cycle = ' -> '.join('/'.join(k) for k in chain + [key])
            raise MsgError(f'recursive message definition: {cycle}')
        state[key] = 'active'
        msg = messages[key]
        for field in msg.fields:
            dep = field.type.msg
            if dep is None:
                continue
            if dep not in messages:
                raise MsgError(f"{msg.path}:{field.line}: unknown message type "
                               f"'{dep[0]}/{dep[1]}' (give its .msg file as an input)")
            visit(dep, chain + [key])
        state[key] = 'done'
        order.append(msg)

    for key in sorted(messages):
        visit(key, [])
    return order


def render(order, inputs):
    out = [
        '// Generated by tests/ros2_compat/msg2idl.py from ROS 2 .msg files; do not edit.',
        '// The types as rmw_cyclonedds_cpp registers them: <pkg>::msg::dds_::<Name>_, keyless,',
        '// plain CDR (XCDR1), members in .msg order. Constants and defaults are not on the wire.',
        '// Inputs:',
    ]
    out += [f'//   {p}' for p in inputs]
    out.append('')
    i = 0
    while i < len(order):
        pkg = order[i].pkg
        out.append(f'module {idl_identifier(pkg)} {{ module msg {{ module dds_ {{')
        while i < len(order) and order[i].pkg == pkg:
            msg = order[i]
            out.append(f'  // {msg.pkg}/{msg.name}')
            out.append(f'  struct {msg.name}_ {{')
            members = []
            for field in msg.fields:
                t, n = field.type, idl_member_name(field.name)
                elem = t.idl_element()
                if t.array == 'fixed':
                    members.append(f'{elem} {n}[{t.size}];')
                elif t.array == 'bounded':
                    members.append(f'sequence<{elem}, {t.size}> {n};')
                elif t.array == 'unbounded':
                    members.append(f'sequence<{elem}> {n};')
                else:
                    members.append(f'{elem} {n};')
            if not members:  # rosidl_adapter/resource/struct.idl.em does the same
                members.append('uint8 structure_needs_at_least_one_member;')
            out += [f'    {m}' for m in members]
            out.append('  };')
            i += 1
        out.append('}; }; };')
        out.append('')
    return '\n'.join(out)


def main(argv):
    ap = argparse.ArgumentParser(
        description='ROS 2 .msg files -> one IDL file, types named as rmw_cyclonedds_cpp '
        'registers them (<pkg>::msg::dds_::<Name>_).')
    ap.add_argument('--out', help='the IDL file to write (default: standard output)')
    ap.add_argument('msgs', nargs='+', metavar='PKG/msg/Name.msg')
    args = ap.parse_args(argv)
    try:
        messages = {}
        for path in args.msgs:
            msg = parse_msg(path)
            if msg.key in messages:
                raise MsgError(f'{path}: {msg.pkg}/{msg.name} is also defined by '
                               f'{messages[msg.key].path}')
            messages[msg.key] = msg
        text = render(topological(messages), args.msgs)
    except (MsgError, OSError, UnicodeDecodeError) as e:
        print(f'msg2idl: {e}', file=sys.stderr)
        return 1
    if args.out is None:
        sys.stdout.write(text)
        return 0
    tmp = args.out + '.tmp'
    try:
        with open(tmp, 'w', encoding='utf-8') as f:
            f.write(text)
        os.replace(tmp, args.out)
    except OSError as e:
        print(f'msg2idl: {args.out}: {e}', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
